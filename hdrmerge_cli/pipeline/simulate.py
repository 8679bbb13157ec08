"""simulate: render a bracket from a scene through the sensor model (16)-(18).

Each frame is rendered with the sensor at its ISO (:meth:`SensorModel.at_iso`,
Hasinoff et al. 2010).  The ground truth is in the units of ``merge``: merge divides
frame ``j`` by ``h_j = t_j ISO_j / ISO_ref`` (``ISO_ref`` the ISO of its first frame, the
shortest ``h``) and scales to ``h_ref``, the geometric mean of the ``h_j``, so
``truth = sqrt(alpha(ISO_ref)) h_ref E / y_max`` (1.0 = the full-scale signal of an
exposure of ``h_ref`` seconds at ``ISO_ref``)."""
from __future__ import annotations

import json
import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hdrmerge_cli._version import __version__
from hdrmerge_cli.core.cfa import REC709_CHROMATICITIES, mosaic
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.errors import HdrMergeError
from hdrmerge_cli.core.scene import procedural_scene
from hdrmerge_cli.core.sensor import SensorModel, auto_exposure_times, expose, gain_pattern, quantise_crf, quantise_raw
from hdrmerge_cli.io.atomic import atomic_paths, output_folder, write_text
from hdrmerge_cli.io.crfspec import resolve_crf
from hdrmerge_cli.io.frames import MIN_RAW_SIDE, read_frame
from hdrmerge_cli.io.images import read_exr, read_header, write_exr, write_ldr
from hdrmerge_cli.io.malloc import available_memory
from hdrmerge_cli.io.metadata import reference_exposure
from hdrmerge_cli.io.noisespec import iso_key
from hdrmerge_cli.io.dng_integer import write_dng
from hdrmerge_cli.io.times import MIN_SECONDS

log = logging.getLogger("hdrmerge_cli")

FORMATS = ("dng", "jpg", "tif", "png")
CFA_PATTERN = "RGGB"
#: shortest exposure time a DNG stores (a 32-bit rational), and any other format
SHORTEST = {"dng": 1e-6}
#: peak memory of a simulation per pixel of the scene (bytes; the built-in scene's
#: temporaries dominate: 2048 x 2048 peaks at 760-810 MB, 1024 x 1024 at 250-300 MB)
BYTES_PER_PIXEL = 170
#: sample types of display-referred images (codes through a tone curve, clipped at white)
LDR_TYPES = ("uint8", "int8", "uint16", "int16")


@dataclass
class SimulateOptions:
    output_dir: Path
    scene: str | None = None
    width: int = 768
    height: int = 512
    downscale: int = 1
    scale: float = 1.0
    frames: int = 5
    times: list[float] | None = None
    repeat: int = 1
    sensor: SensorModel = SensorModel()
    fmt: str = "dng"
    crf: str = "srgb"
    out_bits: int = 8
    #: one ISO for every frame, or one per entry of ``times`` (each (time, ISO) pair
    #: rendered ``repeat`` times); ``sensor`` holds the parameters at ``sensor.base_iso``
    iso: int | list[int] = 100
    aperture: float = 8.0
    seed: int = 0
    overwrite: bool = False


def check_memory(width: int, height: int, what: str) -> None:
    """Refuse, before any work, a scene whose simulation needs more memory than there is."""
    need, have = BYTES_PER_PIXEL * width * height, available_memory()
    if have is not None and need > have:
        raise HdrMergeError(f"{what}: a {width} x {height} scene needs about {need / 1e9:.3g} GB of memory to "
                            f"simulate, more than the {have / 1e9:.3g} GB available; use a smaller one")


def stored_time(folder: Path, fmt: str, t: float, hint: str = "give a longer exposure time") -> float:
    """The exposure time a ``fmt`` file actually stores for ``t`` (EXIF writers round
    some rationals): for JPEG/TIFF/PNG written to a 2 x 2 probe file and read back, so that the frames
    are rendered with exactly the time their metadata states.  A time the file cannot hold
    (it reads back as none) is refused, ``hint`` saying what to change."""
    import tempfile

    if fmt == "dng":  # written as a 32-bit rational by us: exact
        from hdrmerge_cli.io.dng_integer import rational

        num, den = rational(t)
        stored = num / den
    else:
        try:
            fd, probe = tempfile.mkstemp(prefix=".probe.", suffix=f".{fmt}", dir=folder)
        except OSError as exc:
            raise HdrMergeError(f"{folder}: cannot write ({exc.strerror or exc})") from None
        os.close(fd)
        try:
            write_ldr(probe, np.zeros((2, 2, 3), np.uint8), {"ExposureTime": float(t)})
            stored = read_frame(probe).exposure_time
        finally:
            os.unlink(probe)
    if not stored:
        raise HdrMergeError(f"exposure time {t:.3g} s: too short for the EXIF of a {fmt.upper()} file (it reads "
                            f"back as none); {hint}")
    return stored


def load_scene(opts: SimulateOptions) -> tuple[np.ndarray, str]:
    """Scene irradiance in photo-electrons per second, ``(H, W, 3)`` float64: the built-in
    procedural scene, a uniform ``flat`` field (1 per second times --scale: flat-field
    calibration frames), ``dark`` (no light: dark frames) or an EXR."""
    if opts.scene in (None, "builtin", "flat", "dark"):
        check_memory(opts.width, opts.height, f"--size {opts.width}x{opts.height}")
    if opts.scene in (None, "builtin"):
        scene, name = procedural_scene(opts.height, opts.width, opts.seed), "builtin"
    elif opts.scene in ("flat", "dark"):
        value = 1.0 if opts.scene == "flat" else 0.0
        return np.full((opts.height - opts.height % 2, opts.width - opts.width % 2, 3), value * opts.scale), opts.scene
    else:
        width, height, _, kind = read_header(opts.scene)
        if kind in LDR_TYPES:
            raise HdrMergeError(f"{opts.scene}: a {kind} image is display-referred (codes through a tone curve, "
                                "clipped at white), not a scene: its highlights are lost and its values are not "
                                "light; give a scene-linear HDR image (OpenEXR, Radiance .hdr, float TIFF) in "
                                "photo-electrons per second (see --scale)")
        check_memory(width, height, str(opts.scene))
        pixels, _ = read_exr(opts.scene)
        if pixels.shape[-1] >= 3:
            scene = pixels[..., :3].astype(np.float64)
        else:
            scene = np.repeat(pixels[..., :1].astype(np.float64), 3, axis=-1)
        name = str(opts.scene)
        if not np.all(np.isfinite(scene)):
            raise HdrMergeError(f"{opts.scene}: the scene has non-finite values")
        scene = np.clip(scene, 0.0, None)
    if opts.downscale > 1:
        k = opts.downscale
        if min(scene.shape[:2]) // k < 2:
            raise HdrMergeError(f"--downscale {k}: leaves a {scene.shape[1] // k} x {scene.shape[0] // k} scene of "
                                f"{name} ({scene.shape[1]} x {scene.shape[0]}); use a smaller --downscale")
        h, w = scene.shape[0] // k * k, scene.shape[1] // k * k
        scene = scene[:h, :w].reshape(h // k, k, w // k, k, 3).mean(axis=(1, 3))
    h, w = scene.shape[:2]
    h, w = h - h % 2, w - w % 2  # whole CFA periods
    scene = scene[:h, :w]
    if h < 2 or w < 2:
        raise HdrMergeError(f"{name}: a {scene.shape[1]} x {scene.shape[0]} scene is too small (at least 2 x 2)")
    if scene.max() <= 0:
        raise HdrMergeError(f"{name}: the scene is black (no light anywhere; 'dark' simulates dark frames)")
    return scene * opts.scale, name


#: longest exposure time a simulated frame may need (seconds)
MAX_TIME = 1e6


def check_times(times: np.ndarray, signal: np.ndarray, scene_name: str, opts: SimulateOptions,
                sensor: SensorModel) -> None:
    """Refuse exposure times the format cannot store, saying why they came out so: too
    many --frames for the scene (one stop apart or more, the longer ones all clipped), a
    scene too dark or too bright for ``sensor`` (at the frames' ISO) at this --scale, or
    the --times given."""
    shortest, fmt = SHORTEST.get(opts.fmt, MIN_SECONDS), opts.fmt.upper()
    if shortest <= times[0] and times[-1] <= MAX_TIME:
        return
    span = f"a {fmt} stores exposure times from {shortest:g} to {MAX_TIME:g} s"
    if opts.times:
        raise HdrMergeError(f"--times: {times[0]:g} s is too short ({span})")
    if scene_name not in ("flat", "dark"):
        t_min, t_max = auto_exposure_times(signal, sensor, 2)
        stops = float(np.log2(t_max / t_min))
        scene_fits = shortest <= t_min and t_max <= MAX_TIME
        if opts.frames - 1 > stops and (scene_fits or opts.frames - 1 > np.log2(MAX_TIME / shortest)):
            raise HdrMergeError(f"--frames {opts.frames}: one stop apart or more, they span {opts.frames - 1} stops "
                                f"({times[0]:.3g} to {times[-1]:.3g} s; {span}), but {scene_name} covers "
                                f"{stops:.1f}: the frames beyond it would be all clipped; give --frames "
                                f"{max(int(stops) + 1, 2)} or fewer, or --times")
    if times[-1] > MAX_TIME:
        raise HdrMergeError(f"{scene_name}: exposing it takes {times[-1]:.3g} s ({span}): the scene is too dark "
                            "for the sensor; raise --scale or give --times")
    raise HdrMergeError(f"{scene_name}: its brightest parts saturate the sensor in {times[0]:.3g} s ({span}): the "
                        "scene is too bright for the sensor; lower --scale or give --times")


def frame_isos(iso, times) -> list[int]:
    """The ISO of each entry of ``times`` (or the single ISO of the automatic times, for
    ``times`` None): ``iso`` is one ISO for all, or a list as long as ``times``."""
    isos = [iso] if isinstance(iso, (int, np.integer)) else [int(i) for i in iso]
    if not isos or not all(1 <= i <= 65535 for i in isos):
        raise HdrMergeError("--iso: give ISOs from 1 to 65535 (a 16-bit EXIF field)")
    if len(isos) == 1:
        return isos * (len(times) if times else 1)
    if not times:
        raise HdrMergeError(f"--iso: a list of {len(isos)} ISOs pairs with --times, one ISO per exposure time; "
                            "give --times, or a single ISO")
    if len(isos) != len(times):
        raise HdrMergeError(f"--iso: {len(isos)} ISOs for {len(times)} exposure times (--times); give one ISO "
                            "per exposure time, or a single ISO")
    return isos


def _bracket_times(opts: SimulateOptions, signal: np.ndarray, scene_name: str, at_iso: dict,
                   isos: list[int]) -> tuple[np.ndarray, list[int]]:
    """The frames' exposure times ((n,) seconds, camera-rounded, repeated) and ISOs in merge's order, checked."""
    auto = at_iso[isos[0]]  # the automatic times: at the single ISO given
    if opts.times:
        times = np.asarray(opts.times, float)
    elif scene_name == "dark":
        times = np.full(opts.frames, 1.0 / 100)
    elif scene_name == "flat":  # a photon-transfer series: 2 % to 90 % of saturation
        times = np.geomspace(0.02, 0.9, opts.frames) * auto.saturation_electrons / (signal.max())
    else:
        times = auto_exposure_times(signal, auto, opts.frames)
    if not opts.times:
        isos = isos * len(times)
    # rounded as cameras do: 1/n s below 0.1 s, four significant digits above
    times = np.repeat([1.0 / round(1.0 / t) if t < 0.1 else float(f"{t:.4g}") for t in times], opts.repeat)
    isos = np.repeat(isos, opts.repeat)
    order = np.argsort(times * isos, kind="stable")  # merge's order: exposure h = t ISO, shortest first
    times, isos = times[order], [int(i) for i in isos[order]]
    check_times(np.sort(times), signal, scene_name, opts, auto)
    return times, isos


def _simulation_metadata(opts: SimulateOptions, scene_name: str, names: list[str], times: np.ndarray, t_ref: float,
                         at_iso: dict, crf: CRF, out_bits: int, isos: list[int], irradiance: np.ndarray) -> dict:
    """The contents of simulation.json (without ``saturated_fraction``, known once rendered)."""
    sensor = opts.sensor
    return {
        "tool": f"hdrmerge-cli {__version__}",
        "scene": scene_name,
        "format": opts.fmt,
        "frames": names,
        "exposure_times": [float(t) for t in times],
        "reference_exposure": t_ref,
        "sensor": sensor.as_dict(),
        "sensor_at_iso": {iso_key(iso): s.as_dict() for iso, s in at_iso.items()},
        "crf": crf.describe(),
        "out_bits": out_bits if opts.fmt != "dng" else sensor.bits,
        "cfa_pattern": CFA_PATTERN if opts.fmt == "dng" else None,
        "iso": isos[0] if len(set(isos)) == 1 else None,
        "isos": isos,
        "reference_iso": isos[0],
        "seed": opts.seed,
        "truth": "truth.exr",
        "truth_units": "1.0 = full-scale signal at reference_exposure seconds at reference_iso (the units of "
                       "'merge')",
        "width": int(irradiance.shape[1]),
        "height": int(irradiance.shape[0]),
    }


def _write_frame(path, y: np.ndarray, exposure_time: float, iso: int, opts: SimulateOptions, crf: CRF,
                 out_bits: int) -> None:
    """Write the rendered signal ``y`` as a frame of ``opts.fmt`` (raw DNG, or an image through ``crf``)."""
    sensor = opts.sensor
    if opts.fmt == "dng":
        write_dng(
            path, quantise_raw(y, sensor), pattern=CFA_PATTERN, black=sensor.black,
            white=sensor.white, exposure_time=exposure_time, iso=iso, aperture=opts.aperture,
        )
    else:
        write_ldr(path, quantise_crf(y, sensor, crf, out_bits), {
            "ExposureTime": float(exposure_time), "FNumber": float(opts.aperture),
            "Exif:PhotographicSensitivity": iso, "Exif:ISOSpeedRatings": iso,
            "Make": "hdrmerge-cli", "Model": "simulated sensor",
        })


def simulate(opts: SimulateOptions) -> dict:
    if opts.fmt not in FORMATS:
        raise HdrMergeError(f"unknown format {opts.fmt!r} (choose from {', '.join(FORMATS)})")
    sensor = opts.sensor
    isos = frame_isos(opts.iso, opts.times)
    at_iso = {iso: sensor.at_iso(iso) for iso in sorted(set(isos))}
    crf = CRF("linear") if opts.fmt == "dng" else resolve_crf(opts.crf)
    out_bits = 8 if opts.fmt == "jpg" else opts.out_bits
    irradiance, scene_name = load_scene(opts)
    if opts.fmt == "dng" and min(irradiance.shape[:2]) < MIN_RAW_SIDE:
        raise HdrMergeError(f"{scene_name}: LibRaw reads DNGs of at least {MIN_RAW_SIDE} x {MIN_RAW_SIDE} pixels; "
                            + ("use a larger --size or less --downscale" if scene_name in ("builtin", "flat", "dark")
                               else "use less --downscale or a larger scene"))
    rng = np.random.default_rng(opts.seed)
    signal = mosaic(irradiance, CFA_PATTERN) if opts.fmt == "dng" else irradiance
    times, isos = _bracket_times(opts, signal, scene_name, at_iso, isos)
    pattern = gain_pattern(signal.shape, sensor, rng)  # d_i ~ N(0, beta / alpha): the same at every ISO

    out = Path(opts.output_dir)
    if out.exists() and not out.is_dir():
        raise HdrMergeError(f"{out}: exists and is not a folder")
    names = [f"frame_{k:02d}.{opts.fmt}" for k in range(len(times))]
    paths = [out / n for n in names] + [out / "truth.exr", out / "simulation.json"]
    with output_folder(out):  # removed again if the run fails before anything is in it
        requested = times  # what the metadata is written with (rewriting a read-back value can re-round it)
        hint = "give longer --times" if opts.times else "lower --scale or give --times"
        times = np.array([stored_time(out, opts.fmt, t, hint) for t in times])
        # merge's reference exposure, of h_j = t_j ISO_j / ISO_ref (the first frame's ISO)
        t_ref = reference_exposure("geomean", times * np.asarray(isos, float) / isos[0])
        truth = (np.sqrt(at_iso[isos[0]].alpha) * t_ref / sensor.full_scale) * irradiance  # in merge's units
        if float(truth.max()) > np.finfo(np.float32).max:
            raise HdrMergeError(f"{scene_name}: its brightest values times --scale {opts.scale:g} exceed what a float "
                                "EXR holds (truth.exr); lower --scale")
        meta = _simulation_metadata(opts, scene_name, names, times, t_ref, at_iso, crf, out_bits, isos, irradiance)
        saturated = []
        with atomic_paths(paths, opts.overwrite) as tmps:
            for k, t in enumerate(times):
                y = expose(signal, t, at_iso[isos[k]], rng, pattern)
                saturated.append(float(np.mean(y >= sensor.full_scale)))
                _write_frame(tmps[k], y, requested[k], isos[k], opts, crf, out_bits)
                stored = read_frame(tmps[k]).exposure_time
                if stored is None or abs(stored - t) > 1e-5 * t:
                    raise HdrMergeError(f"{names[k]}: the file stores exposure time {stored}, not {t} (internal error)")
                log.info("rendered %s (t = %.6g s, ISO %d, %.1f %% saturated)", names[k], t, isos[k],
                         100 * saturated[-1])
            write_exr(tmps[-2], truth.astype(np.float32), ["R", "G", "B"], {
                "Software": f"hdrmerge-cli {__version__}", "hdrmerge:referenceExposure": t_ref,
                "hdrmerge:units": meta["truth_units"], "chromaticities": list(REC709_CHROMATICITIES),
                "ExposureTime": t_ref})
            meta["saturated_fraction"] = saturated
            write_text(tmps[-1], json.dumps(meta, indent=1) + "\n")
        return {"output_dir": str(out), "files": [str(p) for p in paths]} | meta
