"""What each program does with each kind of frame: ``python -m benchmarks input_kinds``.

Brackets of one simulated scene (three frames 2 EV apart) written as every kind of file a
camera or scanner produces: grey, grey + alpha, RGB and RGBA at 8 and 16 bit, frames one
pixel high, wide or both, Bayer and LinearRaw (RGB, monochrome) DNGs.  Each program merges
them as its user would, from the files, with its default settings:

- ours: ``hdrmerge-cli merge FILES -o out.exr``;
- OpenCV: ``cv2.imread(IMREAD_UNCHANGED)``, ``createCalibrateDebevec`` and ``createMergeDebevec``;
- colour-hdri: frames read by OpenImageIO as floats, ``camera_response_functions_Debevec1997``
  and ``image_stack_to_HDRI``;
- Luminance HDR: ``luminance-hdr-cli -e EV,... -s out.exr FILES``;
- pfstools: ``pfsinhdrgen | pfshdrcalibrate | pfsout out.exr``;
- HDRMerge (RAW only): ``hdrmerge -o out.dng FILES``.

An outcome is ``ok`` (a finite image of the frames' size), ``refused`` (an error message
and no output), ``crash`` (an exception, a traceback or a signal) or ``wrong`` (exit 0 with
no output, non-finite values or the wrong size).  Writes ``results/input_kinds.md``.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

from benchmarks.peers import QT

RESULTS = Path(__file__).parent / "results"
TIMES = (0.0025, 0.01, 0.04)
#: kind name -> (channels, bits, (height, width)), or the RAW kinds by name
IMAGE_KINDS = {
    "grey 8-bit TIFF": (1, 8, None), "grey 16-bit TIFF": (1, 16, None), "grey+alpha 8-bit PNG": (2, 8, None),
    "RGB 8-bit TIFF": (3, 8, None), "RGB 16-bit TIFF": (3, 16, None), "RGBA 8-bit PNG": (4, 8, None),
    "RGB 1 x 64 px": (3, 8, (1, 64)), "RGB 48 x 1 px": (3, 8, (48, 1)), "RGB 1 x 1 px": (3, 8, (1, 1)),
}
RAW_KINDS = ("Bayer DNG", "LinearRaw RGB DNG", "LinearRaw grey DNG")
PROGRAMS = ("hdrmerge-cli", "OpenCV", "colour-hdri", "Luminance HDR", "pfstools", "HDRMerge")


# ---------------------------------------------------------------- the brackets
def _cli() -> str:
    exe = Path(sys.executable).parent / "hdrmerge-cli"
    return str(exe) if exe.exists() else "hdrmerge-cli"


def _image_bracket(src: list[Path], folder: Path, channels: int, bits: int, size) -> list[Path]:
    import OpenImageIO as oiio

    folder.mkdir(parents=True)
    out = []
    for k, path in enumerate(src):
        buf = oiio.ImageBuf(str(path))
        spec = buf.spec()
        px = buf.get_pixels(oiio.UINT8 if bits == 8 else oiio.UINT16)
        if size is not None:
            px = px[: size[0], : size[1]]
        colour = px[..., 1:2] if channels <= 2 else px[..., :3]
        if channels in (2, 4):
            colour = np.concatenate([colour, np.full_like(colour[..., :1], np.iinfo(px.dtype).max)], axis=-1)
        h, w = colour.shape[:2]
        new = oiio.ImageSpec(w, h, channels, oiio.UINT8 if bits == 8 else oiio.UINT16)
        new.attribute("ExposureTime", float(spec.getattribute("ExposureTime")))
        if channels in (2, 4):
            new.alpha_channel = channels - 1
        out.append(folder / f"f{k}{'.png' if channels in (2, 4) else '.tif'}")
        o = oiio.ImageOutput.create(str(out[-1]))
        o.open(str(out[-1]), new)
        o.write_image(np.ascontiguousarray(colour))
        o.close()
    return out


#: DNG PhotometricInterpretation of demosaiced linear data (DNG 1.4 specification)
LINEAR_RAW = 34892


def write_linear_dng(
    path: str,
    pixels: np.ndarray,
    *,
    black: int,
    white: int,
    exposure_time: float,
    iso: int | None = None,
    aperture: float | None = None,
    as_shot_neutral=(1.0, 1.0, 1.0),
    orientation: int = 1,
) -> None:
    """Write ``(H, W, 3)`` (or ``(H, W)`` monochrome) uint16 linear camera RGB as an
    uncompressed LinearRaw DNG (PhotometricInterpretation 34892), the already demosaiced
    data DNG converters and some cameras write; LibRaw reads it back bit-exactly as a
    colour stack.  ``as_shot_neutral``: the camera RGB of white (AsShotNeutral; LibRaw's
    as-shot white balance is its inverse); ``orientation``: the EXIF orientation tag."""
    from pidng.core import DNGTags, Tag
    from pidng.defs import CalibrationIlluminant

    from hdrmerge_cli.io.dng_integer import finish_dng, rational

    from hdrmerge_cli.core.output_colorspace import xyz_to

    xyz_to_camera = xyz_to("rec709")  # camera RGB is linear Rec.709
    pixels = np.ascontiguousarray(pixels, dtype=np.uint16)
    h, w = pixels.shape[:2]
    samples = 1 if pixels.ndim == 2 else pixels.shape[2]
    tags = DNGTags()
    tags.set(Tag.ImageWidth, w)
    tags.set(Tag.ImageLength, h)
    tags.set(Tag.TileWidth, w)
    tags.set(Tag.TileLength, h)
    tags.set(Tag.Orientation, int(orientation))
    tags.set(Tag.PhotometricInterpretation, LINEAR_RAW)
    tags.set(Tag.SamplesPerPixel, samples)
    tags.set(Tag.BitsPerSample, [16] * samples)
    tags.set(Tag.BlackLevel, int(black))
    tags.set(Tag.WhiteLevel, int(white))
    if samples == 3:
        tags.set(Tag.ColorMatrix1, [rational(v, 10000) for v in np.asarray(xyz_to_camera, float).ravel()])
        tags.set(Tag.CalibrationIlluminant1, CalibrationIlluminant.D65)
        tags.set(Tag.AsShotNeutral, [rational(v, 10000) for v in as_shot_neutral])
    finish_dng(tags, path, pixels, exposure_time, iso, aperture, "hdrmerge-cli", "simulated linear camera")


def linear_dng_bracket(folder: Path, mono: bool, shape=(64, 96)) -> list[Path]:
    """Three LinearRaw DNGs (RGB, or monochrome with ``mono``) of a ramp over 10 stops,
    frames of ``shape`` (rows, columns) 2 EV apart (:data:`TIMES`)."""
    from hdrmerge_cli.core.sensor import SensorModel, expose, quantise_raw

    sensor = SensorModel(alpha=0.25, sigma_o2=9.0, bits=14, black=512)
    rng = np.random.default_rng(5)
    ramp = sensor.saturation_electrons * np.geomspace(2.0**-10, 2.0, shape[1]) / 0.01
    scene = np.broadcast_to(ramp, shape) if mono else np.broadcast_to(ramp[:, None], shape + (3,))
    folder.mkdir(parents=True)
    out = []
    for k, t in enumerate(TIMES):
        codes = quantise_raw(expose(np.array(scene), t, sensor, rng, np.zeros(scene.shape)), sensor)
        out.append(folder / f"lin_{k}.dng")
        write_linear_dng(str(out[-1]), codes, black=sensor.black, white=sensor.white, exposure_time=t, iso=100)
    return out


def brackets(root: Path) -> dict[str, list[Path]]:
    times = ",".join(map(str, TIMES))
    sources = {}
    for bits in (8, 16):
        subprocess.run([_cli(), "simulate", "-o", root / f"src{bits}", "--format", "tif", "--out-bits", str(bits),
                        "--size", "96x64", "--times", times, "-q"], check=True)
        sources[bits] = sorted((root / f"src{bits}").glob("frame_*.tif"))
    out = {name: _image_bracket(sources[b], root / f"k{i}", c, b, s)
           for i, (name, (c, b, s)) in enumerate(IMAGE_KINDS.items())}
    subprocess.run([_cli(), "simulate", "-o", root / "dng", "--size", "96x64", "--times", times, "-q"], check=True)
    out["Bayer DNG"] = sorted((root / "dng").glob("frame_*.dng"))
    out["LinearRaw RGB DNG"] = linear_dng_bracket(root / "lin_rgb", mono=False)
    out["LinearRaw grey DNG"] = linear_dng_bracket(root / "lin_grey", mono=True)
    return out


# ---------------------------------------------------------------- the programs
def _tool(cmd, cwd, stdin=None, stdout=subprocess.DEVNULL) -> tuple[int, str]:
    proc = subprocess.run([str(c) for c in cmd], cwd=cwd, stdin=stdin, stdout=stdout, stderr=subprocess.PIPE,
                          env=dict(os.environ, **QT), timeout=300)
    return proc.returncode, proc.stderr.decode(errors="replace")


def _ours(files, out):
    return _tool([_cli(), "merge", *files, "-o", out / "m.exr"], out) + (out / "m.exr",)


def _opencv(files, out):
    import cv2

    frames = [cv2.imread(str(f), cv2.IMREAD_UNCHANGED) for f in files]
    if any(f is None for f in frames):
        return 1, "cv2.imread could not read the files", None
    t = np.asarray(TIMES, np.float32)
    response = cv2.createCalibrateDebevec().process(frames, t)
    hdr = cv2.createMergeDebevec().process(frames, t, response)
    np.save(out / "m.npy", hdr)
    return 0, "", out / "m.npy"


def _colour_hdri(files, out):
    import colour_hdri as ch
    import OpenImageIO as oiio

    stack = ch.ImageStack()
    for f, t in zip(files, TIMES):
        stack.append(ch.Image(data=oiio.ImageBuf(str(f)).get_pixels(oiio.FLOAT),
                              metadata=ch.Metadata(f_number=1.0, exposure_time=t, iso=100.0)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        crfs = ch.camera_response_functions_Debevec1997(stack)
        hdr = ch.image_stack_to_HDRI(stack, camera_response_functions=crfs)
    np.save(out / "m.npy", hdr)
    return 0, "", out / "m.npy"


def _luminance(files, out):
    evs = ",".join(f"{np.log2(t):.6f}" for t in TIMES)
    return _tool(["luminance-hdr-cli", "-e", evs, "-s", out / "m.exr", *files], out) + (out / "m.exr",)


def _pfstools(files, out):
    script = out / "bracket.hdrgen"
    script.write_text("".join(f"{f} {1 / t:g} 1 100 0\n" for f, t in zip(files, TIMES)))
    gen = subprocess.Popen(["pfsinhdrgen", str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    cal = subprocess.Popen(["pfshdrcalibrate", "-c", "robertson"], stdin=gen.stdout, stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE)
    gen.stdout.close()
    code, err = _tool(["pfsout", out / "m.exr"], out, stdin=cal.stdout)
    cal.wait(300)
    gen.wait(300)
    errors = (gen.stderr.read() + cal.stderr.read()).decode(errors="replace") + err
    return max(abs(gen.returncode), abs(cal.returncode), abs(code)), errors, out / "m.exr"


def _hdrmerge(files, out):
    if files[0].suffix.lower() != ".dng":
        return None, "RAW only", None
    return _tool(["hdrmerge", "-b", "32", "-o", out / "m.dng", *files], out) + (out / "m.dng",)


RUNNERS = {"hdrmerge-cli": (_ours, None), "OpenCV": (_opencv, None), "colour-hdri": (_colour_hdri, None),
           "Luminance HDR": (_luminance, "luminance-hdr-cli"), "pfstools": (_pfstools, "pfsinhdrgen"),
           "HDRMerge": (_hdrmerge, "hdrmerge")}


def _read(path: Path) -> np.ndarray:
    if path.suffix == ".npy":
        return np.load(path)
    if path.suffix == ".dng":
        import rawpy

        with rawpy.imread(str(path)) as raw:
            return raw.raw_image_visible.astype(np.float32)
    from hdrmerge_cli.io.images import read_exr

    return read_exr(str(path))[0]


def outcome(program: str, files: list[Path], out: Path, shape) -> tuple[str, float]:
    runner, tool = RUNNERS[program]
    if tool and shutil.which(tool) is None:
        return "not installed", 0.0
    out.mkdir(parents=True)
    t0 = time.perf_counter()
    try:
        code, err, result = runner(files, out)
    except subprocess.TimeoutExpired:
        return "crash: timed out", time.perf_counter() - t0
    except Exception as exc:  # noqa: BLE001 - a library's exception is that peer's crash
        text = " ".join(str(exc).split())
        return f"crash: {type(exc).__name__}: {text[-70:]}", time.perf_counter() - t0
    seconds = time.perf_counter() - t0
    if code is None:
        return "n/a (" + err + ")", 0.0
    last = " ".join((err.strip().splitlines() or [""])[-1].split())[:70]
    if code < 0 or "Traceback" in err:
        return f"crash: {last}", seconds
    if code != 0:
        return ("refused: " if result is None or not result.exists() else "wrong (output left): ") + last, seconds
    if result is None or not result.exists():
        return "wrong: exit 0, no output", seconds
    pixels = _read(result)
    if not np.all(np.isfinite(pixels)):
        return "wrong: non-finite values", seconds
    if pixels.shape[:2] != shape:
        return f"wrong: size {pixels.shape[:2]} for {shape}", seconds
    return "ok", seconds


def main(quick: bool = False) -> str:
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    RESULTS.mkdir(exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        kinds = brackets(root / "in")
        rows, counts = [], {p: 0 for p in PROGRAMS}
        for kind, files in kinds.items():
            from hdrmerge_cli.io.frames import read_frame

            first = read_frame(str(files[0]))
            shape = (first.height, first.width)
            cells = []
            for program in PROGRAMS:
                result, seconds = outcome(program, files, root / "out" / kind.replace(" ", "_") / program, shape)
                counts[program] += result == "ok"
                cells.append(result.replace("|", "/") + (f" ({seconds:.1f} s)" if result == "ok" else ""))
            rows.append(f"| {kind} | " + " | ".join(cells) + " |")
    n = len(kinds)
    table = "\n".join([
        "# Input kinds: what each program does with each kind of frame",
        "",
        "Generated by `python -m benchmarks input_kinds` (see its docstring for how each program is run).",
        "",
        "| kind | " + " | ".join(PROGRAMS) + " |",
        "|---|" + "---|" * len(PROGRAMS),
        *rows,
        "| **kinds merged** | " + " | ".join(f"**{counts[p]} / {n}**" for p in PROGRAMS) + " |",
        "",
    ])
    (RESULTS / "input_kinds.md").write_text(table)
    return table


if __name__ == "__main__":
    print(main())
