"""Speed and memory of the merge, against OpenCV, colour-hdri and the memory-bandwidth floor.

Four measurements, all in one run (ratios are what count; absolute times are noisy):

1. Merge core (decoded frames in memory -> float32 result) for 3, 5 and 9 frames of 6, 24
   and 48 MP: 8-bit RGB frames (JPEG-like, CRF x^0.4) merged with ``triangle`` and the
   noise-optimal ``probabilistic`` weights, against OpenCV ``MergeDebevec`` on the same
   frames, colour-hdri ``image_stack_to_HDRI`` (6 MP only: it works in float64 and needs
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
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from benchmarks import write_result
from hdrmerge_cli.core.crf import CRF
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.reconstruct import merge_frames
from hdrmerge_cli.core.scene import procedural_scene
from hdrmerge_cli.io.plots import pyplot, save_figure

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
    from hdrmerge_cli.core.color import quiet_import

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
acc = LogMerge((4, 4)); acc.add(np.zeros((4, 4), np.uint16), exposure_tables(65536, np.zeros(1), np.full(1, 9.0), CRF("linear"), "triangle", 1.0)); acc.finish(scale=1.0)
import hdrmerge_cli.core.color as c; c.quiet_import("colour_demosaicing")
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


def simulate_dng(folder: Path, width: int, height: int, frames: int) -> list[Path]:
    cli_args = ["simulate", "-o", str(folder), "--size", f"{width}x{height}", "--frames", str(frames), "--overwrite"]
    cli(cli_args)
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
    save_figure(fig, out, overwrite=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="1 MP only, 3 and 5 frames")
    print(main(ap.parse_args().quick))
