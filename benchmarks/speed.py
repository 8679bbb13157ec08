"""Speed and memory of the merge, against OpenCV, colour-hdri and the memory-bandwidth floor.

Four measurements, all in one run (ratios are what count; absolute times are noisy):

1. Merge core (decoded frames in memory -> float32 result, the frames streamed through the
   fused kernels of the merge's first pass, :func:`benchmarks.core_merge.merge_frames`) for
   3, 5 and 9 frames of 6, 24 and 48 MP: 8-bit RGB frames (JPEG-like, CRF x^0.4) merged
   with ``triangle`` and the noise-optimal ``probabilistic`` weights, against OpenCV
   ``MergeDebevec`` on the same frames, colour-hdri ``image_stack_to_HDRI`` (6 MP only: it works in float64 and needs
   ~30 bytes per sample per frame), and the floor: the time to read every input buffer
   once (a two-thread sum over the bytes) and the lookup floor (one table read per sample).
   Also 14-bit Bayer mosaics (RAW-like, ML).
2. End-to-end ``hdrmerge-cli merge`` on simulated 14-bit DNG brackets against the sum of
   LibRaw decode times of its frames (rawpy ``imread`` + ``raw_image_visible``).
3. Peak memory of ``merge`` (a fresh process per run; peak RSS above the RSS after imports)
   against one decoded frame plus the merge accumulators (``num``, ``den``: 8 bytes per
   sample) and the RGB float32 result, for 3 and 9 frames.
4. ``estimate-crf`` on 8-bit JPEG brackets (5 frames) and ``calibrate-noise`` on one
   24 MP DNG frame, as a user runs them (fresh process), beside the time to decode their
   inputs and the command's start-up.

    python -m benchmarks.speed [--quick]   # writes benchmarks/results/speed.md and speed.png
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from benchmarks import save_figure, write_result
from benchmarks.core_merge import merge_frames
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.scene import procedural_scene
from hdrmerge_cli.io.plots import pyplot

RESULTS = Path(__file__).parent / "results"
GAMMA = 2.5  # gamma^-1(v) = v^2.5, the paper's x^0.4 CRF
#: the steps of ``merge --json``'s timing_seconds, in order
STEPS = ("read_metadata", "noise_estimate", "tables", "decode_and_merge_wall", "irls", "color_and_write")


@numba.njit(parallel=True, nogil=True, cache=True)
def _read_all(words):  # pragma: no cover
    """Sum of every 64-bit word of one buffer, both cores: the cost of reading it once."""
    total = np.uint64(0)
    for i in numba.prange(words.shape[0]):
        total += words[i]
    return total


def read_floor(buffers) -> float:
    """Seconds to read every buffer once (best of 3)."""
    views = [np.ascontiguousarray(b).reshape(-1).view(np.uint8)[: b.nbytes // 8 * 8].view(np.uint64) for b in buffers]
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        for v in views:
            _read_all(v)
        best = min(best, time.perf_counter() - t)
    return best


@numba.njit(parallel=True, nogil=True, cache=True)
def _lookup_all(codes, table):  # pragma: no cover
    """Sum of ``table[code]`` over one buffer, both cores: the least work any table-driven
    merge does per sample (one code read and one table read)."""
    total = np.float32(0.0)
    for i in numba.prange(codes.shape[0]):
        total += table[codes[i]]
    return total


def lookup_floor(buffers) -> float:
    """Seconds to look every code of every buffer up in a table once (best of 3)."""
    flat = [np.ascontiguousarray(b).reshape(-1) for b in buffers]
    table = np.linspace(0.0, 1.0, int(np.iinfo(flat[0].dtype).max) + 1, dtype=np.float32)
    best = np.inf
    for _ in range(3):
        t = time.perf_counter()
        for v in flat:
            _lookup_all(v, table)
        best = min(best, time.perf_counter() - t)
    return best


def best_of(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def bracket_8bit(mp: float, n_frames: int, seed: int = 0):
    """``n_frames`` uint8 (H, W, 3) frames of the built-in scene tiled to ``mp`` megapixels,
    2 EV apart, through the CRF x^0.4 with a little noise; returns frames and times."""
    base = procedural_scene(512, 768, seed)
    base = base / np.percentile(base, 99.9)
    w = int(round(np.sqrt(mp * 1e6 * 1.5) / 8)) * 8
    h = int(round(mp * 1e6 / w / 8)) * 8
    scene = np.tile(base, (-(-h // 512), -(-w // 768), 1))[:h, :w].astype(np.float32)
    rng = np.random.default_rng(seed)
    times = 2.0 ** (2 * np.arange(n_frames) - 2 * (n_frames // 2))
    noise = rng.normal(0, 0.004, scene.shape[:2] + (1,)).astype(np.float32)
    frames = []
    for t in times:
        v = np.clip(scene * np.float32(t) + noise, 0, 1) ** np.float32(1 / GAMMA)
        frames.append(np.rint(v * 255).astype(np.uint8))
    return frames, times


def mosaic_14bit(frames_8bit):
    """14-bit Bayer mosaics (RGGB) from the same scene: linear codes with black 512."""
    out = []
    for f in frames_8bit:
        lin = (f[::, ::, 1].astype(np.float32) / 255) ** GAMMA
        out.append((np.rint(lin * (16383 - 512)) + 512).astype(np.uint16))
    return out


def core_speed(mp: float, n_frames: int, with_colour: bool) -> dict:
    import cv2

    frames, times = bracket_8bit(mp, n_frames)
    crf = CRF("gamma", GAMMA)
    prior = float(np.mean(crf.inverse(frames[n_frames // 2][..., 1][::97, ::89] / 255.0)) * 255 / times[n_frames // 2])
    noise = [NoiseParams(1.0, 1.0, 0.0)]
    repeat = 3 if mp < 10 else 2
    row = {"mp": frames[0].shape[0] * frames[0].shape[1] / 1e6, "frames": n_frames, "bytes": sum(f.nbytes for f in frames)}
    row["floor"] = read_floor(frames)
    row["lookup"] = lookup_floor(frames)
    row["triangle"] = best_of(lambda: merge_frames(frames, times, crf, 0.0, 255.0, "triangle"), repeat)
    row["probabilistic"] = best_of(lambda: merge_frames(frames, times, crf, 0.0, 255.0, "probabilistic", noise,
                                                        prior_rate=prior), repeat)
    response = np.repeat(crf.inverse(np.arange(256) / 255.0).astype(np.float32)[:, None, None], 3, axis=2)
    response = np.maximum(response, 1e-6)
    debevec = cv2.createMergeDebevec()
    row["opencv_debevec"] = best_of(lambda: debevec.process(frames, times.astype(np.float32), response), 1)
    if with_colour:
        row["colour_hdri"] = best_of(lambda: colour_merge(frames, times), 1)
    mosaics = mosaic_14bit(frames)
    pattern = np.array([[0, 1], [1, 2]])
    raw_noise = [NoiseParams(9.0, 0.25, 0.0)] * 3
    row["raw_floor"] = read_floor(mosaics)
    row["raw_ml"] = best_of(lambda: merge_frames(mosaics, times, CRF("linear"), [512.0] * 3, [16383.0] * 3,
                                                 "probabilistic", raw_noise, estimator="ml", prior_rate=1e4,
                                                 pattern=pattern), repeat)
    return row


def colour_merge(frames, times):
    """colour-hdri's Debevec-weighted merge with the known CRF, as its docs show."""
    from benchmarks import quiet_import

    ch = quiet_import("colour_hdri")
    stack = ch.ImageStack()
    for f, t in zip(frames, times):
        stack.append(ch.Image(data=f / 255.0, metadata=ch.Metadata(f_number=8.0, exposure_time=float(t), iso=100)))
    grid = np.linspace(0, 1, 256)
    crfs = np.stack([CRF("gamma", GAMMA).inverse(grid)] * 3, axis=-1)
    return ch.image_stack_to_HDRI(stack, camera_response_functions=crfs)


# ---------------------------------------------------------------- CLI runs in fresh processes
PROBE = r"""
import json, sys, time
from click.testing import CliRunner
from hdrmerge_cli.cli import cli as main
from hdrmerge_cli.core.reconstruct import LogMerge, exposure_tables
from hdrmerge_cli.core.crf import CRF
import numpy as np
acc = LogMerge((4, 4)); acc.add(np.zeros((4, 4), np.uint16), exposure_tables(CRF("linear").at_codes(65536, np.zeros(1), np.full(1, 9.0)), "triangle", 1.0)); acc.finish(scale=1.0)
import hdrmerge_cli.core.cfa_to_rgb  # the colour kernel (compiled, cached)
if sys.argv[1] in main.list_commands(None): main.get_command(None, sys.argv[1])  # its imports, before the base RSS
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096
base = rss()
t = time.perf_counter()
res = CliRunner().invoke(main, sys.argv[1:], catch_exceptions=False)
wall = time.perf_counter() - t
# VmHWM: this process's own peak (ru_maxrss would report the forking parent's peak when
# that was larger: Linux carries it across fork and exec)
peak = next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith("VmHWM:"))
print(json.dumps({"exit": res.exit_code, "wall": wall, "base": base, "peak": peak, "out": res.output[-20000:]}))
"""


def cli(args: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-c", PROBE, *args], capture_output=True, text=True, check=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if res["exit"] != 0:
        raise RuntimeError(f"hdrmerge-cli {' '.join(args)} failed: {res['out']}")
    return res


def command_seconds(args: list[str]) -> float:
    """Wall time of ``hdrmerge-cli ARGS`` in a fresh interpreter, imports included."""
    t = time.perf_counter()
    subprocess.run([sys.executable, "-m", "hdrmerge_cli", *args], capture_output=True, check=True)
    return time.perf_counter() - t


def decode_sum(paths) -> float:
    """Seconds to decode every 8-bit image once with OpenImageIO (one thread)."""
    import OpenImageIO as oiio

    total = 0.0
    for p in paths:
        t = time.perf_counter()
        inp = oiio.ImageInput.open(str(p))
        inp.read_image(0, 0, 0, 3, format=oiio.UINT8)
        inp.close()
        total += time.perf_counter() - t
    return total


def libraw_decode_sum(paths) -> float:
    import rawpy

    total = 0.0
    for p in paths:
        t = time.perf_counter()
        with rawpy.imread(str(p)) as raw:
            raw.raw_image_visible.copy()
        total += time.perf_counter() - t
    return total


def simulate_dng(folder: Path, width: int, height: int, frames: int, times: str | None = None) -> list[Path]:
    cli_args = ["simulate", "-o", str(folder), "--size", f"{width}x{height}", "--overwrite"]
    cli(cli_args + (["--times", times] if times else ["--frames", str(frames)]))
    return sorted(folder.glob("frame_*.dng"))


def end_to_end(tmp: Path, width: int, height: int, n_frames: int) -> dict:
    paths = simulate_dng(tmp / f"raw{n_frames}", width, height, n_frames)
    decode = min(libraw_decode_sum(paths) for _ in range(2))
    runs = [cli(["merge", *map(str, paths), "-o", str(tmp / "m.exr"), "--overwrite", "--json"]) for _ in range(2)]
    best = min(runs, key=lambda r: r["wall"])
    steps = json.loads(best["out"])["timing_seconds"]
    n = width * height
    return {"mp": n / 1e6, "frames": n_frames, "decode_sum": decode, "wall": best["wall"], "steps": steps,
            "peak": max(r["peak"] - r["base"] for r in runs), "frame_bytes": 2 * n, "acc_bytes": 8 * n,
            "rgb_bytes": 12 * n, "paths": paths}


def jpeg_bracket(folder: Path, mp: float, n_frames: int = 5) -> list[Path]:
    import OpenImageIO as oiio

    frames, times = bracket_8bit(mp, n_frames, seed=1)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, (f, t) in enumerate(zip(frames, times)):
        spec = oiio.ImageSpec(f.shape[1], f.shape[0], 3, oiio.UINT8)
        spec.attribute("ExposureTime", float(t))
        spec.attribute("Compression", "jpeg:95")
        p = folder / f"f{k}.jpg"
        out = oiio.ImageOutput.create(str(p))
        out.open(str(p), spec)
        out.write_image(f)
        out.close()
        paths.append(p)
    return paths


# ---------------------------------------------------------------- whole commands
GNU_TIME = "/usr/bin/time"
OPENCV_SCRIPT = r"""
import os, sys, time
os.environ["OPENCV_IO_ENABLE_OPENEXR"] = "1"
import cv2, numpy as np
out, times, paths = sys.argv[1], [float(t) for t in sys.argv[2].split(",")], sys.argv[3:]
images = [cv2.imread(p, cv2.IMREAD_COLOR) for p in paths]
v = np.arange(256) / 255.0
response = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)  # sRGB, known
response = np.repeat(np.maximum(response, 1e-6)[:, None, None], 3, axis=2)
hdr = cv2.createMergeDebevec().process(images, np.array(times, np.float32), response)
try:
    ok = cv2.imwrite(out, hdr.astype(np.float32))
except cv2.error:  # an OpenCV build without OpenEXR: write it with OpenImageIO (uncompressed float, RGB)
    import OpenImageIO as oiio
    rgb = np.ascontiguousarray(hdr[..., ::-1], np.float32)
    spec = oiio.ImageSpec(rgb.shape[1], rgb.shape[0], 3, "float")
    spec.attribute("compression", "none")
    o = oiio.ImageOutput.create(out); o.open(out, spec); o.write_image(rgb); o.close()
"""


def timed(cmd: list[str], env: dict | None = None, timeout: float = 1800) -> dict | None:
    """Wall seconds and peak RSS (GNU time's %M, the command's own: ru_maxrss of a forked
    child carries the parent's size) of one command as a user runs it; None if it failed."""
    with tempfile.NamedTemporaryFile("r", suffix=".time") as tf:
        full = ([GNU_TIME, "-f", "%M", "-o", tf.name] if os.path.exists(GNU_TIME) else []) + cmd
        t = time.perf_counter()
        try:
            res = subprocess.run(full, capture_output=True, text=True, env=os.environ | (env or {}), timeout=timeout)
        except subprocess.TimeoutExpired:
            return None
        wall = time.perf_counter() - t
        if res.returncode != 0:
            print(f"failed: {' '.join(cmd)}\n{res.stderr[-2000:]}", file=sys.stderr)
            return None
        peak = None
        if os.path.exists(GNU_TIME):
            lines = [ln for ln in tf.read().split() if ln.strip().isdigit()]
            peak = int(lines[-1]) * 1024 if lines else None
    return {"wall": wall, "peak": peak, "stdout": res.stdout}


def best_timed(cmd, env=None, repeat: int = 2, timeout: float = 1800) -> dict | None:
    runs = [r for r in (timed(cmd, env, timeout) for _ in range(repeat)) if r]
    if not runs:
        return None
    best = min(runs, key=lambda r: r["wall"])
    return best | {"peak": max((r["peak"] or 0) for r in runs) or None}


def ours() -> list[str]:
    exe = Path(sys.executable).with_name("hdrmerge-cli")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "hdrmerge_cli"]


def as_camera(paths: list[Path], folder: Path, make: str = "BenchCam", model: str = "Sim 14-bit") -> list[Path]:
    """The simulated DNGs rewritten with a camera make/model (simulated sensors are never
    put in the noise cache), bit-identical mosaics."""
    import rawpy

    from hdrmerge_cli.io.frames import read_frame
    from hdrmerge_cli.io.dng_integer import write_dng

    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for p in paths:
        f = read_frame(str(p))
        with rawpy.imread(str(p)) as raw:
            mosaic = raw.raw_image_visible.copy()
        dst = folder / p.name
        write_dng(str(dst), mosaic, pattern=f.cfa_pattern, black=int(f.black[0]), white=int(f.white[0]),
                  exposure_time=f.exposure_time, iso=int(f.iso), make=make, model=model, xyz_to_camera=np.eye(3))
        out.append(dst)
    return out


def import_ms(args: list[str]) -> float:
    """Sum of the top-level cumulative import times (``python -X importtime``) of a command."""
    code = "import sys; sys.argv = ['hdrmerge-cli'] + sys.argv[1:]; from hdrmerge_cli.cli import main; main()"
    res = subprocess.run([sys.executable, "-X", "importtime", "-c", code, *args], capture_output=True, text=True)
    total = 0
    for line in res.stderr.splitlines():
        parts = line.split("|")
        if line.startswith("import time:") and len(parts) == 3 and not parts[2].startswith("  ") \
                and parts[1].strip().isdigit():
            total += int(parts[1])
    return total / 1000


def ev_list(paths) -> str:
    """``luminance-hdr-cli -e``: each frame's exposure in EV relative to the first (it reads
    no exposure from these DNGs' EXIF)."""
    from hdrmerge_cli.io.frames import read_frame

    times = [read_frame(str(p)).exposure_time for p in paths]
    return ",".join(f"{np.log2(t / times[0]):.4f}" for t in times)


def merge_split(stdout: str) -> dict:
    try:
        return json.loads(stdout)["timing_seconds"]
    except (ValueError, KeyError):
        return {}


def _row(rows: list[str], case: str, tool: str, r: dict | None, ref: float | None = None, extra: str = "") -> None:
    """Append one table row of :func:`whole_commands`: wall time, its ratio to ``ref`` and peak RSS."""
    if r is None:
        rows.append(f"| {case} | {tool} | failed / skipped | - | - | {extra} |")
        return
    ratio = f"{r['wall'] / ref:.2f}" if ref else "-"
    peak = f"{r['peak'] / 1e6:.0f}" if r.get("peak") else "-"
    rows.append(f"| {case} | {tool} | {r['wall']:.2f} | {ratio} | {peak} | {extra} |")


def _whole_tiff(tmp: Path, quick: bool, luminance: str | None, row) -> None:
    """The 8-bit TIFF case of :func:`whole_commands` (3 x 12 MP; quick: 2 MP): ours (default
    options: the response measured on the bracket; and given sRGB, as OpenCV is), OpenCV and
    Luminance HDR as table rows through ``row``."""
    tw, th = (1728, 1152) if quick else (4240, 2832)
    tif_dir = tmp / "tif"
    cli(["simulate", "-o", str(tif_dir), "--size", f"{tw}x{th}", "--frames", "3", "--format", "tif", "--crf", "srgb",
         "--overwrite"])
    tifs = sorted(tif_dir.glob("frame_*.tif"))
    times = json.loads((tif_dir / "simulation.json").read_text())["exposure_times"]
    ocv = best_timed([sys.executable, "-c", OPENCV_SCRIPT, str(tmp / "tif_cv.exr"), ",".join(map(str, times)),
                      *map(str, tifs)], None, 2)
    cmd = ours() + ["merge", *map(str, tifs), "-o", str(tmp / "tif.exr"), "--overwrite", "--json"]
    ours_first = first_merge(cmd, tmp)
    ours_srgb = first_merge(cmd + ["--crf", "srgb"], tmp)
    lum_tif = best_timed([luminance, "-s", str(tmp / "tif_lum.exr"), *map(str, tifs)], None, 1, timeout=900) \
        if luminance else None
    ref = ocv["wall"] if ocv else None
    case = f"3 x {tw * th / 1e6:.0f} MP 8-bit TIFF"
    row(case, "hdrmerge-cli merge: first merge (default options: response measured)", ours_first, ref, split="first")
    row(case, "hdrmerge-cli merge --crf srgb (response given, as to OpenCV)", ours_srgb, ref, split="--crf srgb")
    row(case, "OpenCV imread + MergeDebevec (known sRGB response) + EXR write", ocv, ref,
        "python + cv2 start-up included; EXR by OpenImageIO (uncompressed) where cv2 has no OpenEXR")
    row(case, "luminance-hdr-cli -s out.exr", lum_tif, ref, "" if luminance else "not installed")
    # memory: 9 frames against 3 (the 3 copied three times, the response given as above)
    nine = tmp / "tif_nine"
    nine.mkdir()
    copies = []
    for k in range(9):
        copies.append(nine / f"frame_{k:02d}.tif")
        shutil.copyfile(tifs[k % 3], copies[-1])
    ours_nine = first_merge(ours() + ["merge", *map(str, copies), "-o", str(tmp / "tif9.exr"), "--overwrite", "--json",
                                      "--crf", "srgb"], tmp, 1)
    ratio = ours_nine["peak"] / ours_srgb["peak"] if ours_nine and ours_srgb and ours_srgb["peak"] else None
    row(f"9 x {tw * th / 1e6:.0f} MP 8-bit TIFF", "hdrmerge-cli merge --crf srgb", ours_nine, None,
        f"peak 9 / 3 frames = {ratio:.2f}" if ratio else "")


def _whole_lines(rows: list[str], startup: dict, splits: list, t_load) -> list[str]:
    """The markdown of :func:`whole_commands`: its table rows, start-up times and stage splits."""
    lines = ["## Whole commands as a user runs them", "",
             f"Fresh process per run, wall time (best of 2-3) and peak RSS from GNU time (`%M`).  Load average at the "
             f"start {t_load[0]:.1f} on {os.cpu_count()} cores (other jobs shared the machine: ratios measured back to "
             "back are what count).  The DNGs are simulated (`simulate`, 14-bit, uncompressed) and rewritten with a "
             "camera make, so that the per-camera noise cache applies.  *First merge*: a camera's first merge, with "
             "default options and an empty cache (a new cache folder for every run); *cached*: the camera's next "
             "merge, its noise read from the cache.  'ratio' is against the case's first peer (HDRMerge for DNG, "
             "OpenCV for TIFF).", "",
             "| case | tool | wall s | ratio | peak MB | note |", "|---|---|---|---|---|---|", *rows, "",
             "Start-up (no work done): wall time and the sum of the top-level imports (`python -X importtime`).", "",
             "| command | wall s | imports ms |", "|---|---|---|"]
    for k, (wall, imp) in startup.items():
        lines.append(f"| `hdrmerge-cli {k}` | {wall:.2f} | {imp:.0f} |")
    steps = ("read_metadata", "response", "align", "exposure_check", "noise_estimate", "tables",
             "decode_and_merge_wall", "irls", "color_and_write")
    lines += ["", "Per-stage split of each of our runs above (`merge --json` timing_seconds; stages overlap on two "
              "cores, so they need not add up to the wall time):", "",
              "| case | run | " + " | ".join(steps) + " |", "|---|---|" + "---|" * len(steps)]
    for case, name, st in splits:
        lines.append(f"| {case} | {name} | " + " | ".join(f"{st.get(k, 0.0):.2f}" for k in steps) + " |")
    return lines


def first_merge(cmd: list[str], tmp: Path, repeat: int = 2) -> dict | None:
    """Best of ``repeat`` runs of ``cmd``, each a camera's first merge: a new, empty cache
    folder per run."""
    runs = []
    for k in range(repeat):
        folder = tmp / f"fresh-cache-{time.monotonic_ns()}-{k}"
        runs.append(timed(cmd, {"HDRMERGE_CLI_CACHE_DIR": str(folder)}))
        shutil.rmtree(folder, ignore_errors=True)
    runs = [r for r in runs if r]
    if not runs:
        return None
    return min(runs, key=lambda r: r["wall"]) | {"peak": max((r["peak"] or 0) for r in runs) or None}


def handheld_dng(tmp: Path, width: int, height: int) -> list[Path] | None:
    """A hand-held RAW bracket of 3 frames (:mod:`benchmarks.motion`'s first case drawn at
    this size: shifts up to 20 px, rotations up to 2 degrees, a moving object), or None
    without the real HDR scenes it renders."""
    from benchmarks import motion

    names = motion.scene_names()
    if not names:
        return None
    case = motion.draw_case(0, width, height, names)
    return list(motion.render(case, tmp / "handheld").moving)


def whole_commands(tmp: Path, quick: bool) -> list[str]:
    """Whole commands as a user runs them, against HDRMerge, Luminance HDR and OpenCV on the
    same files: markdown lines of the table."""
    hdrmerge = shutil.which("hdrmerge")
    luminance = shutil.which("luminance-hdr-cli")
    qt = {"QT_QPA_PLATFORM": "offscreen"}
    cache = {"HDRMERGE_CLI_CACHE_DIR": str(tmp / "noise-cache")}
    rows, splits = [], []
    t_load = os.getloadavg()

    def row(case, tool, r, ref=None, extra="", split=None):
        _row(rows, case, tool, r, ref, extra)
        if split and r:
            splits.append((case, split, merge_split(r["stdout"])))

    def hdrmerge_run(paths, out, repeat=2):
        return best_timed([hdrmerge, "-b", "32", "-o", str(out), *map(str, paths)], qt, repeat) if hdrmerge else None

    startup = {}
    for args in (["--help"], ["merge", "--help"]):
        r = best_timed(ours() + args, repeat=3)
        startup[" ".join(args)] = (r["wall"] if r else float("nan"), min(import_ms(args) for _ in range(2)))

    # small bracket: 4 x 0.4 MP DNG
    small = as_camera(simulate_dng(tmp / "small_sim", 768, 512, 4), tmp / "small")
    small_cmd = ours() + ["merge", *map(str, small), "-o", str(tmp / "small.exr"), "--overwrite", "--json"]
    hm_small = hdrmerge_run(small, tmp / "small_hm.dng", 3)
    ours_small_first = first_merge(small_cmd, tmp, 3)
    timed(small_cmd, cache)  # fills the cache
    ours_small = best_timed(small_cmd, cache, 3)
    ref = hm_small["wall"] if hm_small else None
    case = "4 x 0.4 MP DNG"
    row(case, "hdrmerge-cli merge: first merge (default options, empty cache)", ours_small_first, ref, split="first")
    row(case, "hdrmerge-cli merge: cached", ours_small, ref, split="cached")
    row(case, "HDRMerge -b 32 (float DNG)", hm_small, ref, "" if hdrmerge else "not installed")

    # big RAW bracket: 24 MP x 3 (quick: 6 MP)
    w, h = (3000, 2000) if quick else (6000, 4000)
    big = as_camera(simulate_dng(tmp / "big_sim", w, h, 3), tmp / "big")
    mp = w * h / 1e6
    decode = min(libraw_decode_sum(big) for _ in range(2))
    big_cmd = ours() + ["merge", *map(str, big), "-o", str(tmp / "big.exr"), "--overwrite", "--json"]
    hm_big = hdrmerge_run(big, tmp / "big_hm.dng")
    ours_first = first_merge(big_cmd, tmp)
    timed(big_cmd, cache)  # fills the cache
    ours_big = best_timed(big_cmd, cache, 2)
    ours_big_dng = best_timed(big_cmd[:big_cmd.index("-o") + 1] + [str(tmp / "big.dng"), "--overwrite", "--json"],
                              cache, 2)
    lum_big = best_timed([luminance, "-e", ev_list(big), "-s", str(tmp / "big_lum.exr"), *map(str, big)], None, 1,
                         timeout=900) if luminance and not quick else None
    ref = hm_big["wall"] if hm_big else None
    case = f"{mp:.0f} MP x 3 DNG"
    row(case, "hdrmerge-cli merge: first merge (default options, empty cache)", ours_first, ref,
        f"{ours_first['wall'] / decode:.1f}x LibRaw decode sum ({decode:.2f} s)" if ours_first else "", split="first")
    row(case, "hdrmerge-cli merge: cached", ours_big, ref, split="cached")
    row(case, "hdrmerge-cli merge -o out.dng (float DNG, as HDRMerge), cached", ours_big_dng, ref, split="-o out.dng")
    row(case, "HDRMerge -b 32 (float DNG)", hm_big, ref, "" if hdrmerge else "not installed")
    row(case, "luminance-hdr-cli -s out.exr", lum_big, ref, "" if luminance else "not installed")

    # memory: 9 vs 3 frames (the 3 frames copied three times: same bytes per frame; copies, as
    # merge refuses one file given twice)
    nine = tmp / "nine"
    nine.mkdir()
    links = []
    for k in range(9):
        dst = nine / f"frame_{k:02d}.dng"
        shutil.copyfile(big[k % 3], dst)
        links.append(dst)
    ours_nine = timed(ours() + ["merge", *map(str, links), "-o", str(tmp / "nine.exr"), "--overwrite", "--json"],
                      cache)
    hm_nine = hdrmerge_run(links, tmp / "nine_hm.dng", 1)
    mem_ratio = (ours_nine["peak"] / ours_big["peak"]) if ours_nine and ours_big and ours_big["peak"] else None
    case = f"{mp:.0f} MP x 9 DNG"
    ref = hm_nine["wall"] if hm_nine else None
    row(case, "hdrmerge-cli merge: cached", ours_nine, ref, f"peak 9 / 3 frames = {mem_ratio:.2f}" if mem_ratio else "")
    row(case, "HDRMerge -b 32 (float DNG)", hm_nine, ref, "" if hdrmerge else "not installed")

    # the commonest camera bracket: 3 frames 2 EV apart (the simulated default spans about 8 EV)
    two = as_camera(simulate_dng(tmp / "two_ev_sim", w, h, 3, times="1/400,1/100,1/25"), tmp / "two_ev")
    hm_two = hdrmerge_run(two, tmp / "two_hm.dng")
    ours_two = first_merge(ours() + ["merge", *map(str, two), "-o", str(tmp / "two.exr"), "--overwrite", "--json"],
                           tmp)
    case = f"{mp:.0f} MP x 3 DNG, 2 EV apart"
    ref = hm_two["wall"] if hm_two else None
    row(case, "hdrmerge-cli merge: first merge (default options, empty cache)", ours_two, ref, split="first")
    row(case, "HDRMerge -b 32 (float DNG)", hm_two, ref, "" if hdrmerge else "not installed")

    # hand-held RAW bracket: alignment needed (HDRMerge aligns by default too)
    moving = handheld_dng(tmp, w, h)
    case = f"{mp:.0f} MP x 3 DNG, hand-held"
    if moving is None:
        rows.append(f"| {case} | - | skipped | - | - | no real HDR scenes in ../shared/data/hdr |")
    else:
        hm_moving = hdrmerge_run(moving, tmp / "moving_hm.dng")
        ours_moving = first_merge(ours() + ["merge", *map(str, moving), "-o", str(tmp / "moving.exr"), "--overwrite",
                                            "--json"], tmp)
        ref = hm_moving["wall"] if hm_moving else None
        row(case, "hdrmerge-cli merge: first merge (default options: aligned)", ours_moving, ref, split="first")
        row(case, "HDRMerge -b 32 (float DNG; aligns by default)", hm_moving, ref, "" if hdrmerge else "not installed")

    _whole_tiff(tmp, quick, luminance, row)
    return _whole_lines(rows, startup, splits, t_load)


def main_whole(quick: bool = False) -> str:
    """Only the whole-command comparison: benchmarks/results/speed_whole[_quick].md."""
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        lines = whole_commands(Path(tmp), quick)
    lines = ["# Speed: whole commands", "", f"Run took {time.perf_counter() - t_start:.0f} s.", ""] + lines[2:]
    return write_result(RESULTS / ("speed_whole_quick.md" if quick else "speed_whole.md"), lines)


def main(quick: bool = False) -> str:
    t_start = time.perf_counter()
    sizes = (1.0,) if quick else (6.0, 24.0, 48.0)
    counts = (3, 5) if quick else (3, 5, 9)
    rows = [core_speed(mp, k, with_colour=mp <= 6) for mp in sizes for k in counts]

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        w, h = (1536, 1024) if quick else (6000, 4000)
        e2e = [end_to_end(tmp, w, h, k) for k in ((3,) if quick else (3, 9))]
        crf_rows = []
        for mp in ((1.0,) if quick else (6.0, 24.0, 48.0)):
            paths = jpeg_bracket(tmp / f"jpg{mp:g}", mp)
            wall = min(command_seconds(["estimate-crf", *map(str, paths), "-o", str(tmp / "crf.json"), "--overwrite"])
                       for _ in range(2))
            crf_rows.append((mp, wall, decode_sum(paths)))
        one = e2e[0]["paths"][len(e2e[0]["paths"]) // 2]
        cal = {"wall": min(command_seconds(["calibrate-noise", str(one), "-o", str(tmp / "noise.json"), "--overwrite"])
                           for _ in range(2)), "decode": libraw_decode_sum([one])}
        startup = {c: min(command_seconds([c, "--help"]) for _ in range(2)) for c in ("estimate-crf", "calibrate-noise")}
        whole = whole_commands(tmp, quick)

    lines = ["# Speed and memory", "",
             f"{os.cpu_count()} cores; numba {numba.__version__} with {numba.get_num_threads()} threads; "
             f"run took {time.perf_counter() - t_start:.0f} s.  Times are the best of 2-3 runs (OpenCV and "
             "colour-hdri: one run); ratios matter, not absolute values.", "",
             "## Merge core: decoded frames in memory -> float32 result", "",
             "8-bit RGB frames, CRF x^0.4 known, log estimator.  'floor' = reading every input byte once "
             "(two threads; this machine's 480 MB L3 cache holds most brackets, so it runs at cache, not DRAM, "
             "speed); 'lookup' = one table read per input sample (two threads), the least work of any table-driven "
             "merge.  colour-hdri only at 6 MP (float64, too much memory beyond).", "",
             "| MP | frames | floor ms | lookup ms | triangle s | probabilistic s | prob./triangle | prob./floor "
             "| prob./lookup | OpenCV Debevec s | OpenCV / prob. | colour-hdri s | colour / prob. |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        col = (f"{r['colour_hdri']:.2f} | {r['colour_hdri'] / r['probabilistic']:.0f}x" if "colour_hdri" in r else "- | -")
        lines.append(f"| {r['mp']:.1f} | {r['frames']} | {r['floor'] * 1e3:.1f} | {r['lookup'] * 1e3:.0f} "
                     f"| {r['triangle']:.3f} | {r['probabilistic']:.3f} "
                     f"| {r['probabilistic'] / r['triangle']:.2f} | {r['probabilistic'] / r['floor']:.1f}x "
                     f"| {r['probabilistic'] / r['lookup']:.1f}x "
                     f"| {r['opencv_debevec']:.2f} | {r['opencv_debevec'] / r['probabilistic']:.0f}x | {col} |")
    lines += ["", "14-bit Bayer mosaics (RAW-like), ML estimator, probabilistic weights, per-CFA-channel tables:", "",
              "| MP | frames | floor ms | merge s | merge/floor | ns per sample per frame |", "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['mp']:.1f} | {r['frames']} | {r['raw_floor'] * 1e3:.1f} | {r['raw_ml']:.3f} | "
                     f"{r['raw_ml'] / r['raw_floor']:.1f}x | {r['raw_ml'] / (r['mp'] * 1e6 * r['frames']) * 1e9:.2f} |")
    lines += ["", "## End-to-end `hdrmerge-cli merge` on 14-bit DNG brackets (defaults: noise measured on the bracket, "
              "demosaic, EXR)", "",
              "| MP | frames | LibRaw decode sum s | merge wall s | wall / decode | peak MB | one frame + accumulators MB "
              "| peak / (frame + acc.) | + RGB result MB | peak / (frame + acc. + RGB) |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for r in e2e:
        fa = r["frame_bytes"] + r["acc_bytes"]
        lines.append(f"| {r['mp']:.1f} | {r['frames']} | {r['decode_sum']:.2f} | {r['wall']:.2f} | "
                     f"{r['wall'] / r['decode_sum']:.2f} | {r['peak'] / 1e6:.0f} | {fa / 1e6:.0f} | {r['peak'] / fa:.2f} | "
                     f"{(fa + r['rgb_bytes']) / 1e6:.0f} | {r['peak'] / (fa + r['rgb_bytes']):.2f} |")
    lines += ["", "Where the time goes (seconds, the best run): decode+merge is the streamed pass (LibRaw decoding "
              "overlapped with the fused merge); the simulated DNGs are uncompressed, so LibRaw's decode is little more "
              "than a copy and the fixed steps (noise estimate, tables, demosaic, EXR compression) dominate.", "",
              "| MP | frames | " + " | ".join(STEPS) + " | decode+merge / decode sum |", "|---|---|" + "---|" * (len(STEPS) + 1)]
    for r in e2e:
        st = r["steps"]
        lines.append(f"| {r['mp']:.1f} | {r['frames']} | " + " | ".join(f"{st.get(k, 0.0):.2f}" for k in STEPS)
                     + f" | {st['decode_and_merge_wall'] / r['decode_sum']:.2f} |")
    lines += ["", "## Other commands (`hdrmerge-cli ...` in a fresh process, wall time, best of 2)", "",
              "'decode' = reading the inputs once (OpenImageIO / LibRaw, one thread); 'startup' = "
              "`hdrmerge-cli COMMAND --help`, the interpreter and the command's module imports (estimate-crf "
              "imports cvxpy, ~0.9 s, only when it solves).", "",
              "| command | input | s | decode s | startup s |", "|---|---|---|---|---|"]
    for mp, t, dec in crf_rows:
        lines.append(f"| estimate-crf | 5 JPEG frames of {mp:g} MP | {t:.2f} | {dec:.2f} | {startup['estimate-crf']:.2f} |")
    lines.append(f"| calibrate-noise | one {e2e[0]['mp']:.0f} MP DNG frame | {cal['wall']:.2f} "
                 f"| {cal['decode']:.2f} | {startup['calibrate-noise']:.2f} |")
    lines += [""] + whole
    text = write_result(RESULTS / ("speed_quick.md" if quick else "speed.md"), lines)
    plot(rows, RESULTS / ("speed_quick.png" if quick else "speed.png"))
    return text


def plot(rows, out: Path) -> None:
    fig, ax = pyplot().subplots(figsize=(7, 4.5))
    samples = np.array([r["mp"] * r["frames"] for r in rows])
    order = np.argsort(samples)
    for key, label in (("floor", "read floor"), ("triangle", "hdrmerge triangle"),
                       ("probabilistic", "hdrmerge probabilistic"), ("opencv_debevec", "OpenCV MergeDebevec")):
        ax.loglog(samples[order], np.array([r[key] for r in rows])[order], "o-", label=label)
    col = [(r["mp"] * r["frames"], r["colour_hdri"]) for r in rows if "colour_hdri" in r]
    if col:
        ax.loglog(*zip(*col), "s", label="colour-hdri")
    ax.set_xlabel("megapixels x frames (8-bit RGB)")
    ax.set_ylabel("seconds")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    ax.set_title("Merge core time against input size")
    fig.tight_layout()
    save_figure(fig, out)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="1 MP only, 3 and 5 frames")
    ap.add_argument("--whole", action="store_true",
                    help="only the whole-command comparison with HDRMerge, Luminance HDR and OpenCV")
    a = ap.parse_args()
    print(main_whole(a.quick) if a.whole else main(a.quick))
