"""Alignment and ghost removal on randomised brackets nobody tuned to.

Protocol (everything seeded: case ``i`` of a run uses ``numpy.random.default_rng(SEED + i)``;
32 cases in the full run, 6 with ``--quick``, ``--cases N`` to change it)
---------------------------------------------------------------------------------------------

**Scenes.**  The real HDR images in ``../shared/data/hdr/*.exr`` (ScanLines_Desk, _MtTamWest,
_StillLife; the tool's defaults were not chosen on them).  Per case: one scene at random, a
random quarter turn and mirror, resampled (area down / cubic up) by a random factor so that a
random crop of ``W + 2P`` x ``H + 2P`` fits (``W x H`` = 1000 x 700 full, 400 x 300 quick;
pad ``P`` = 64 px), blurred by a Gaussian of sigma 1 px (the lens; without it the scene is not
band-limited, and resampling it -- cubic ringing at edges of 10^4 contrast -- costs more than
any alignment error: the round trip cubic render + exact inverse linear warp of a sharp crop
has an RMS log error of 0.14, 0.026 at sigma 1), scaled so its 99.9th percentile is 1.

**Motion.**  ``N`` = 3 frames (every 4th case 5), the reference is the middle one
(``hdrmerge_cli.io.metadata.reference_index``: ``N // 2`` in exposure order) and is not
moved; every other frame gets a rotation about the frame centre, uniform in +-2 degrees, and
a translation uniform in +-20 px in x and y.  Frame pixel ``p`` sees the scene at
``R (p - c) + c + t`` (``c`` the centre), rendered by ``cv2.warpAffine`` (INTER_CUBIC) from the
padded crop.  The true warp from reference to frame coordinates (the convention of merge's
``alignment.warps``) is therefore ``p = R^T (r - c - t) + c``.

**Exposure.**  EV step uniform in [1, 3] stops, times ``t_k = t_0 2^(step k)``; the scene
is scaled so that its 99.9th percentile reaches a log-uniform fraction in [0.05, 0.5] of
saturation in the shortest frame (so the short frame is always dark; the longest clips).

**Ghosts.**  One object per case, an ellipse or a rectangle (random aspect 0.5-2) of 2-10 %
of the frame's area at a random place inside the frame, flat colour of random brightness
(log-uniform between the scene's 1st and 99.9th percentile, x 0.5..2, random tint +-20 %),
pasted into the scene of one random frame only (any frame, the reference included), at the
same scene position (so its footprint in reference coordinates is known exactly).

**Sensor.**  RAW (every other case): ``core.sensor`` (Poisson photons, Gaussian read noise;
``SensorModel()``: 14 bit, black 512, alpha 0.25, sigma_o^2 9), RGGB mosaic, written with
``io.dng_integer.write_dng``.  8-bit (the other cases): the same noise on a 12-bit linear converter
(sqrt(alpha) = 1, sigma_o = 2 codes, black 0), then gamma 2.2 (``x^(1/2.2)``) to 8-bit codes,
written as lossless 8-bit TIFF with EXIF ExposureTime and merged with ``--crf gamma:2.2``.
The *static* twin of a case is the same bracket without motion and without the ghost (same
noise draws, frame for frame; its reference frame is bit-identical when the ghost is
elsewhere).

**Runs** (each one whole ``hdrmerge-cli merge ... --json`` command in a fresh subprocess,
``--reference`` fixed to the reference frame's time; RAW with ``--cfa``, so that the merged
mosaic is scored per CFA site and demosaicing errors, large on these sharp real scenes, stay
out of the score; 8-bit with ``--crf gamma:2.2``): static twin plain (``--align off
--deghost off``; the baseline), static twin ``--align auto --deghost auto`` (false
rejections, cost), moving ``--align auto --deghost auto`` (what a user gets), moving
``--align similarity --deghost auto`` (rotation asked for explicitly; not run again when the
``auto`` run already reports ``motion: similarity``: the table then repeats it), and the ghost
oracle (below).  Wall time and peak RSS of the whole command: ``/usr/bin/time -f %M`` when
present, else ``resource.getrusage(RUSAGE_CHILDREN)`` in a fresh Python per run.  Last, the
oracle of registration (:func:`merge_true_warps`, the Python API in this process): the moving
bracket merged as ``auto`` does but with the true warps, so that the merge's loss against the
static twin splits into the registration's and the resampling's.

**Size.**  The cost targets are stated at 6 and 24 MP: the full run also renders one moving
bracket at 3000 x 2000 (8-bit; case 1's draw at that size) and one at 6000 x 4000 (RAW; case
0's) and times a plain merge against ``--align auto --deghost auto`` on it
(:data:`LARGE_REPEATS` of each, alternating; medians), with the alignment's error (no
static twin, no peers).

**Scores.**

- *Alignment error* (per non-reference frame, the case's worst frame reported): warps from
  the ``alignment`` of merge's ``--json`` summary (the profile JSON does not carry them),
  (2, 3) matrices reference -> frame coordinates.  *shift error* = distance between the
  estimated and true position of the frame centre (the true rotation is about the centre, so
  this is the translation); *corner error* = largest such distance over the 4 corners and the
  centre; *rotation error* = difference of ``atan2(w10, w00)`` in degrees.  A case
  "recovers the shift" when every frame's shift error is <= 0.2 px; the dark short frame
  (frame 0) is also reported alone.
- *PSNR* of log E (8-bit: mean of R, G, B; RAW: per CFA site against the mosaicked truth)
  against the reference frame's truth (the scene, with the ghost only when it is in the
  reference), ``20 log10(peak / RMS)`` after one global scale (median log ratio, ghost
  footprint excluded) per output, ``peak`` = log range of the static truth over the scored
  pixels: those that every frame truly covers (4 px inside that) and that are measurable
  (every channel >= 2 % of full scale in the longest frame, none >= 95 % in the shortest:
  pixels dark or clipped in every frame are noise or a bound, the same in every output, and
  would drown the motion's effect); the output floored at 1 % of the smallest truth.
  *dPSNR* = moving - static plain (target: >= -0.5 dB).  Also without the
  ghost footprint (dilated 8 px): the cost of motion alone.
- *Ghost pixels removed.*  Footprint F0 = ghost pixels in reference coordinates (covered,
  inside the border) where the ghost's log contrast ``|c| = |log(ghost / background)|`` (RGB
  mean) is >= 0.2.  The *oracle* is what a perfect ghost detector could keep: the static
  twin without the ghost's frame (ghost in a non-reference frame), or the moving bracket's
  reference frame alone (ghost in the reference: the reference's content is the truth there),
  merged plain.  F = F0 where the oracle's |log error| is <= min(|c| / 2, 0.3) (the pixels a
  ghost remover can get right at all: not where the only frames without the ghost are clipped
  or dark there); tolerance = max(0.05, 99th percentile of the oracle's
  |log error| over F) + 1e-4 (round-off); *removed* = fraction of F whose |log error| is
  within the tolerance.  That needs the detection and a reconstruction as good as the
  oracle's, which is not resampled: detection alone is the fraction of F where the ``auto``
  run dropped some frame (``--extra-channels ghost`` > 0).  It reads 0 where the ghost's
  frame carries no weight anyway (too dark or clipped there: nothing to drop), and counts a
  pixel where a ghost in the reference made some, not all, of the other frames dropped.
- *False rejections*: ``deghost.rejected_fraction`` of merge's summary, the largest over the
  frames (fraction of cells), on the static twins and on the real static brackets.
- *Cost*: time and peak RSS of the moving bracket's ``--align auto --deghost auto`` over
  the plain merge of its static twin (same size, frames, options); real brackets: auto/auto
  over plain on the same frames.  Run one after the other, so a loaded machine slows both.

**Peers.**  OpenCV ``cv2.createAlignMTB()`` (defaults: 6 pyramid levels, so shifts up to
+-64 px, integer px): ``calculateShift(reference, frame)`` on 8-bit grey versions (8-bit cases:
the channel mean of the TIFF codes; RAW: 2x2-cell means, black subtracted, through x^(1/2.2),
shifts x2 to mosaic px); it is translation-only, scored on the centre shift.  HDRMerge
(``hdrmerge -b 32 -o out.dng FRAMES``, its defaults: alignment on, crop; RAW cases only, it
reads no TIFF): it writes an aligned float CFA DNG but no warps, so its alignment is scored
by the PSNR of its output (2x2-cell means of the CFA against those of the mosaicked truth,
over the measurable cells as above where its output is positive: outside its crop it is 0),
located on the truth by phase correlation (integer cells; against each frame's truth, the
best kept: it may align to a frame other than our reference), moving minus static twin, so
its dPSNR is comparable with ours, not its PSNR.

**Real brackets** (``../shared/data/brackets``, ``--crf srgb`` = the default response):
the hand-held ``iphone6_window_jpg``, ``stack_handheld_jpg``, the ghost ``stack_ghost_jpg``
and ``em1ii_kitchen_jpg``, whose lamps are lit in its three shorter frames only (no truth:
displacements found, cells rejected, and AlignMTB's shifts for comparison), and the static
ones (every other bracket: false rejections, cost).

    python -m benchmarks.motion [--quick]   # benchmarks/results/motion.md (motion_quick.md)
"""
from __future__ import annotations

import dataclasses

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from benchmarks import revision, write_result

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RESULTS = Path(__file__).parent / "results"
SEED = 1700
PAD = 64
BLUR = 1.0  # px, Gaussian sigma of the optics
INNER = 4  # px inside the truly covered region
ORACLE_MAX = 0.3  # ghost pixels scored: the oracle's |log error| below min(|c| / 2, this)
MIN_SIGNAL = 0.02  # scored pixels reach this fraction of full scale in the longest frame (every channel)
TIMEOUT = 900
MAX_SHIFT, MAX_ROT = 20.0, 2.0
SHIFT_TOL, ROT_TOL, PSNR_TOL, GHOST_TARGET, REJECT_TOL = 0.2, 0.05, 0.5, 0.95, 0.002
TIME_RATIO, MEM_RATIO = 2.0, 1.5
GAMMA = 2.2
HANDHELD = ("iphone6_window_jpg", "stack_handheld_jpg")
GHOST = ("stack_ghost_jpg",)
#: on a tripod, but the light changed: em1ii_kitchen_jpg's pendant and ceiling lamps are lit in
#: its three shorter frames (1/40-1/15 s) and off in the two longer ones (1/13, 1/6 s), which
#: deghosting rightly rejects there (seen in the frames; the README of ../shared calls it static)
LIGHTING = ("em1ii_kitchen_jpg",)
#: the cost targets' sizes, 6 and 24 MP: one moving bracket each, (case
#: index, width, height); even indices are RAW, odd 8-bit (:func:`draw_case`)
LARGE = ((0, 6000, 4000), (1, 3000, 2000))
#: plain and auto/auto merges of each of them, alternating; the medians are reported (single
#: runs of the 24 MP bracket spread by 2.13-2.29x between two runs of one code)
LARGE_REPEATS = 3
SETTINGS = {"plain": ("off", "off"), "auto": ("auto", "auto"), "similarity": ("similarity", "auto")}


def cli() -> str:
    beside = Path(sys.executable).with_name("hdrmerge-cli")
    return str(beside) if beside.exists() else (shutil.which("hdrmerge-cli") or "hdrmerge-cli")


# --- running a command: wall time and peak RSS -------------------------------------------

_RUSAGE = ("import resource, subprocess, sys; p = subprocess.run(sys.argv[1:]); "
           "sys.stderr.write('\\nMAXRSS_KB=%d\\n' % resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss); "
           "sys.exit(p.returncode)")


def measured(cmd, cwd, env=None) -> tuple[str, float, float]:
    """Run ``cmd``; (stdout, wall seconds, peak RSS MiB of the command)."""
    cmd = [str(c) for c in cmd]
    with tempfile.NamedTemporaryFile(suffix=".rss", delete=False) as f:
        rss_file = f.name
    if Path("/usr/bin/time").exists():
        full = ["/usr/bin/time", "-f", "%M", "-o", rss_file, *cmd]
    else:
        full = [sys.executable, "-c", _RUSAGE, *cmd]
    t = time.perf_counter()
    try:
        proc = subprocess.run(full, cwd=cwd, capture_output=True, env=dict(os.environ, **(env or {})), timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{Path(cmd[0]).name} timed out after {TIMEOUT} s") from None
    wall = time.perf_counter() - t
    err = proc.stderr.decode(errors="replace")
    try:
        if full[0] == "/usr/bin/time":
            kb = float(Path(rss_file).read_text().strip().splitlines()[-1])
        else:
            kb = float(err.rsplit("MAXRSS_KB=", 1)[1].split()[0])
    except (ValueError, IndexError, OSError):
        kb = float("nan")
    finally:
        Path(rss_file).unlink(missing_ok=True)
    if proc.returncode != 0:
        tail = [ln for ln in err.strip().splitlines() if "MAXRSS_KB" not in ln][-1:] or [""]
        raise RuntimeError(f"{Path(cmd[0]).name} failed (exit {proc.returncode}): {tail[0][:200]}")
    return proc.stdout.decode(errors="replace"), wall, kb / 1024


def merge(paths, out: Path, align: str, deghost: str, extra=()) -> dict:
    """One ``hdrmerge-cli merge`` run: its --json summary plus ``_s``, ``_mib``, ``_rgb``."""
    cmd = [cli(), "merge", *paths, "-o", out, "--align", align, "--deghost", deghost, "--json", "-q",
           "--overwrite", *extra]
    stdout, wall, mib = measured(cmd, out.parent)
    s = json.loads(stdout)
    if "alignment" not in s:  # the profile may carry it one day
        prof = json.loads(Path(s.get("profile", out.with_name(out.stem + ".profile.json"))).read_text())
        if "alignment" in prof:
            s["alignment"] = prof["alignment"]
    s.update(read_output(out))
    s["_s"], s["_mib"] = wall, mib
    return s


def read_output(out: Path) -> dict:
    """A merge's EXR: ``_rgb`` (the mosaic Y of ``--cfa``, else R, G, B; float64) and, with
    ``--extra-channels ghost``, ``_ghost`` (how many frames each pixel lost)."""
    from hdrmerge_cli.io.images import read_exr

    pixels, attrs = read_exr(str(out))
    names = list(attrs["channelnames"])
    got = {"_rgb": (pixels[..., names.index("Y")] if "Y" in names
                    else pixels[..., [names.index(c) for c in "RGB"]]).astype(np.float64)}
    if "ghost" in names:
        got["_ghost"] = pixels[..., names.index("ghost")]
    return got


def merge_true_warps(paths, out: Path, warps, extra=()) -> np.ndarray:
    """The oracle of registration: the bracket merged as ``merge(paths, out, "auto", "auto",
    extra)`` does, but with the frames brought onto the reference by their true ``warps``
    instead of the estimated ones (the Python API in this process, its alignment step
    replaced).  What is then lost against the static twin is the resampling's (and the
    deghosting's), not the registration's.  Returns the output as :func:`merge`'s ``_rgb``."""
    import hdrmerge_cli
    from hdrmerge_cli.pipeline import run as pipeline_run  # the runner calls the registration stage

    align = pipeline_run.align

    def true_alignment(*args, **kwargs):
        found = align(*args, **kwargs)
        return dataclasses.replace(found, warps=[np.asarray(w, np.float64) for w in warps], applied=True,
                                   motion="similarity",
                                   resampling="per-colour" if found.resampling != "none" else "none")

    opts = {"align": "auto", "deghost": "auto", "overwrite": True}
    it = iter(extra)
    for flag in it:  # merge_options' flags as API options
        if flag == "--cfa":
            opts["cfa"] = True
        else:
            opts[flag.lstrip("-")] = next(it)
    pipeline_run.align = true_alignment
    try:
        hdrmerge_cli.merge_files([str(p) for p in paths], **opts).write(str(out))
    finally:
        pipeline_run.align = align
    return read_output(out)["_rgb"]


# --- scenes and brackets -----------------------------------------------------------------

_SCENES: dict[str, np.ndarray] = {}


def scene_names() -> list[str]:
    return sorted(p.stem for p in (DATA / "hdr").glob("*.exr"))


def load_scene(name: str) -> np.ndarray:
    if name not in _SCENES:
        from hdrmerge_cli.io.images import read_exr

        img = read_exr(str(DATA / "hdr" / f"{name}.exr"))[0][..., :3].astype(np.float32)
        _SCENES[name] = np.nan_to_num(np.clip(img, 0, None))
    return _SCENES[name]


@dataclass
class Case:
    index: int
    fmt: str  # "raw" or "8bit"
    n: int
    step: float
    dark: float  # shortest frame: 99.9th percentile at this fraction of saturation
    scene: str
    rot: list  # degrees per frame
    shift: list  # (tx, ty) per frame
    ghost_frame: int
    ghost: dict = field(default_factory=dict)
    width: int = 0
    height: int = 0

    @property
    def ref(self) -> int:
        return self.n // 2

    def true_warp(self, k: int) -> np.ndarray:
        a = np.radians(self.rot[k])
        r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        c = np.array([(self.width - 1) / 2, (self.height - 1) / 2])
        t = np.array(self.shift[k])
        return np.hstack([r.T, (c - r.T @ (c + t))[:, None]])

    def sample_map(self, k: int) -> np.ndarray:
        """(2, 3) frame pixel -> padded-crop coordinates."""
        a = np.radians(self.rot[k])
        r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        c = np.array([(self.width - 1) / 2, (self.height - 1) / 2])
        return np.hstack([r, (c + np.array(self.shift[k]) + PAD - r @ c)[:, None]])


def draw_case(i: int, width: int, height: int, names: list[str]) -> Case:
    rng = np.random.default_rng(SEED + i)
    n = 5 if i % 4 == 3 else 3
    ref = n // 2
    rot = [0.0 if k == ref else float(rng.uniform(-MAX_ROT, MAX_ROT)) for k in range(n)]
    shift = [(0.0, 0.0) if k == ref else tuple(float(v) for v in rng.uniform(-MAX_SHIFT, MAX_SHIFT, 2))
             for k in range(n)]
    area = rng.uniform(0.02, 0.10) * width * height
    aspect = rng.uniform(0.5, 2.0)
    ellipse = bool(rng.random() < 0.5)
    # ellipse area pi a b, rectangle 4 a b (a, b half-axes)
    a = np.sqrt(area * aspect / (np.pi if ellipse else 4.0))
    b = a / aspect
    cx = rng.uniform(a + 8, width - a - 8) if width > 2 * a + 16 else width / 2
    cy = rng.uniform(b + 8, height - b - 8) if height > 2 * b + 16 else height / 2
    ghost = {"shape": "ellipse" if ellipse else "rectangle", "cx": float(cx), "cy": float(cy), "a": float(a),
             "b": float(b), "level": float(rng.uniform(0, 1)), "gain": float(np.exp(rng.uniform(np.log(0.5), np.log(2)))),
             "tint": [float(v) for v in rng.uniform(0.8, 1.2, 3)], "area": float(area / (width * height))}
    return Case(i, "raw" if i % 2 == 0 else "8bit", n, float(rng.uniform(1, 3)),
                float(np.exp(rng.uniform(np.log(0.05), np.log(0.5)))), names[int(rng.integers(len(names)))], rot, shift,
                int(rng.integers(n)), ghost, width, height)


def crop_scene(case: Case) -> np.ndarray:
    """The padded crop ``(H + 2P, W + 2P, 3)``, 99.9th percentile 1."""
    rng = np.random.default_rng(SEED + 10_000 + case.index)
    img = np.rot90(load_scene(case.scene), int(rng.integers(4)))
    if rng.random() < 0.5:
        img = img[:, ::-1]
    hh, ww = case.height + 2 * PAD, case.width + 2 * PAD
    need = max(hh / img.shape[0], ww / img.shape[1])
    k = need * rng.uniform(1.0, 1.25) if need > 1 else rng.uniform(need, min(1.0, 2 * need))
    size = (max(ww, int(round(img.shape[1] * k))), max(hh, int(round(img.shape[0] * k))))
    img = cv2.resize(np.ascontiguousarray(img), size, interpolation=cv2.INTER_AREA if k < 1 else cv2.INTER_CUBIC)
    y0, x0 = int(rng.integers(img.shape[0] - hh + 1)), int(rng.integers(img.shape[1] - ww + 1))
    big = np.clip(img[y0:y0 + hh, x0:x0 + ww].astype(np.float64), 0, None)
    big = cv2.GaussianBlur(big, (0, 0), BLUR)  # the lens: band-limits the scene (see the docstring)
    big /= np.percentile(big.mean(axis=-1), 99.9)
    return np.maximum(big, 1e-6)


def ghost_mask(case: Case, height: int, width: int, offset: float) -> np.ndarray:
    g = case.ghost
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    u, v = (x - offset - g["cx"]) / g["a"], (y - offset - g["cy"]) / g["b"]
    return (u * u + v * v <= 1) if g["shape"] == "ellipse" else ((np.abs(u) <= 1) & (np.abs(v) <= 1))


@dataclass
class Rendered:
    case: Case
    times: np.ndarray
    moving: list  # paths
    static: list
    truth: np.ndarray  # (H, W, 3) the reference frame's scene (the ghost only if it is there)
    truth_static: np.ndarray
    frame_truths: list  # per frame, its scene without the ghost (frame coordinates)
    footprint: np.ndarray  # (H, W) bool, reference coordinates
    contrast: np.ndarray  # (H, W) log(ghost / background)
    covered: np.ndarray  # (H, W) bool, covered by every frame, INNER px inside
    gray8: list  # per moving frame, 8-bit grey image for AlignMTB
    cell: int  # AlignMTB image px -> frame px
    measurable: object  # truth (H, W, 3) -> (H, W) bool: scored pixels (see the docstring)


def render(case: Case, folder: Path) -> Rendered:
    from hdrmerge_cli.core.cfa import mosaic
    from hdrmerge_cli.core.sensor import SensorModel, expose, quantise_crf, quantise_raw
    from hdrmerge_cli.core.crf import parse_crf
    from hdrmerge_cli.io.images import write_ldr
    from hdrmerge_cli.io.dng_integer import write_dng

    w, h = case.width, case.height
    big = crop_scene(case)
    lo, hi = np.percentile(big.mean(axis=-1), [1, 99.9])
    g = case.ghost
    level = np.exp(np.log(lo) + g["level"] * (np.log(hi) - np.log(lo))) * g["gain"]
    mask_big = ghost_mask(case, *big.shape[:2], PAD)
    big_g = big.copy()
    big_g[mask_big] = level * np.array(g["tint"])
    raw = case.fmt == "raw"
    sensor = SensorModel() if raw else SensorModel(alpha=1.0, sigma_o2=4.0, bits=12, black=0)
    crf = parse_crf(f"gamma:{GAMMA}")
    t0 = 1 / 500
    times = t0 * 2.0 ** (case.step * np.arange(case.n))
    k_e = case.dark * sensor.full_scale / (np.sqrt(sensor.alpha) * t0)  # electrons / s for scene value 1
    (folder / "moving").mkdir(parents=True)
    (folder / "static").mkdir()
    moving, static, frame_truths, gray8 = [], [], [], []

    def sample(src, m):
        return np.stack([cv2.warpAffine(src[..., c].astype(np.float32), m.astype(np.float32), (w, h),
                                        flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP, borderMode=cv2.BORDER_REFLECT)
                         for c in range(3)], axis=-1).astype(np.float64)

    ident = np.float64([[1, 0, PAD], [0, 1, PAD]])
    for k, t in enumerate(times):
        for kind in ("moving", "static"):
            src = big_g if (kind == "moving" and k == case.ghost_frame) else big
            scene = np.maximum(sample(src, case.sample_map(k) if kind == "moving" else ident), 0.0)
            if kind == "moving":
                frame_truths.append(np.maximum(sample(big, case.sample_map(k)), 1e-6))
            rng = np.random.default_rng([SEED, case.index, k])  # same draws for the static twin
            if raw:
                z = quantise_raw(expose(mosaic(scene * k_e, "RGGB"), t, sensor, rng, np.zeros((h, w))), sensor)
                p = folder / kind / f"f{k}.dng"
                write_dng(str(p), z, pattern="RGGB", black=sensor.black, white=sensor.white, exposure_time=float(t),
                          iso=100)
                if kind == "moving":
                    cells = (z.astype(np.float64) - sensor.black).reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))
                    gray8.append(np.rint(255 * np.clip(cells / sensor.full_scale, 0, 1) ** (1 / GAMMA)).astype(np.uint8))
            else:
                z = quantise_crf(expose(scene * k_e, t, sensor, rng, np.zeros((h, w, 3))), sensor, crf, 8)
                p = folder / kind / f"f{k}.tif"
                write_ldr(str(p), z, {"ExposureTime": float(t), "FNumber": 4.0, "Make": "simulated"})
                if kind == "moving":
                    gray8.append(np.rint(z.astype(np.float64).mean(axis=-1)).astype(np.uint8))
            (moving if kind == "moving" else static).append(p)

    truth_static = big[PAD:PAD + h, PAD:PAD + w]
    # measurable: every channel >= MIN_SIGNAL of full scale in the longest frame, none above 95 % in the shortest
    y_unit = k_e * np.sqrt(sensor.alpha) / sensor.full_scale  # fraction of full scale per scene unit and second

    def measured(t):
        return (t.min(axis=-1) * y_unit * times[-1] >= MIN_SIGNAL) & (t.max(axis=-1) * y_unit * times[0] < 0.95)
    truth = (big_g if case.ghost_frame == case.ref else big)[PAD:PAD + h, PAD:PAD + w]
    footprint = mask_big[PAD:PAD + h, PAD:PAD + w]
    contrast = np.log(np.mean(level * np.array(g["tint"]))) - np.log(truth_static.mean(axis=-1))
    # covered: reference pixels that land inside every frame, INNER px inside it
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    covered = measured(truth_static) & (x >= INNER) & (x <= w - 1 - INNER) & (y >= INNER) & (y <= h - 1 - INNER)
    for k in range(case.n):
        m = case.true_warp(k)
        fx, fy = m[0, 0] * x + m[0, 1] * y + m[0, 2], m[1, 0] * x + m[1, 1] * y + m[1, 2]
        covered &= (fx >= INNER) & (fx <= w - 1 - INNER) & (fy >= INNER) & (fy <= h - 1 - INNER)
    return Rendered(case, times, moving, static, truth, truth_static, frame_truths, footprint, contrast, covered,
                    gray8, 2 if raw else 1, measured)


# --- scoring ------------------------------------------------------------------------------


def log_error(out: np.ndarray, truth: np.ndarray, region: np.ndarray) -> np.ndarray:
    """(H, W) log error after one global scale (median over ``region``): of the RGB mean, or
    per CFA site when ``out`` is a mosaic (RAW merged with ``--cfa``; the truth mosaicked)."""
    if out.ndim == 2:
        from hdrmerge_cli.core.cfa import mosaic

        t, o = mosaic(truth, "RGGB"), out
    else:
        t, o = truth.mean(axis=-1), out.mean(axis=-1)
    o = np.nan_to_num(o, nan=0.0, posinf=0.0)
    o = np.maximum(o, 0.01 * t[t > 0].min())
    d = np.log(o) - np.log(t)
    return d - np.median(d[region])


def psnr(err: np.ndarray, region: np.ndarray, peak: float) -> float:
    return float(20 * np.log10(peak / np.sqrt(np.mean(err[region] ** 2))))


def warp_errors(case: Case, warps) -> dict:
    """Per non-reference frame: shift (centre), corner and rotation errors."""
    w, h = case.width, case.height
    pts = np.array([[(w - 1) / 2, (h - 1) / 2, 1], [0, 0, 1], [w - 1, 0, 1], [0, h - 1, 1], [w - 1, h - 1, 1]], float)
    out = {"shift": [], "corner": [], "rot": []}
    for k in range(case.n):
        if k == case.ref:
            continue
        est, tru = np.asarray(warps[k], float), case.true_warp(k)
        d = np.hypot(*((pts @ est.T) - (pts @ tru.T)).T)
        out["shift"].append(float(d[0]))
        out["corner"].append(float(d.max()))
        out["rot"].append(abs(float(np.degrees(np.arctan2(est[1, 0], est[0, 0]) - np.arctan2(tru[1, 0], tru[0, 0])))))
    return out


def mtb_shift(ref: np.ndarray, img: np.ndarray) -> np.ndarray:
    """AlignMTB's displacement of ``img`` against ``ref`` in ``ref -> img`` coordinates (x, y):
    calculateShift gives how to shift ``img`` to match ``ref``, the displacement is minus that."""
    s = cv2.createAlignMTB().calculateShift(ref, img)
    return -np.array(s, float)


def score_mtb(r: Rendered) -> dict:
    case = r.case
    c = np.array([(case.width - 1) / 2, (case.height - 1) / 2])
    errs, t = [], time.perf_counter()
    for k in range(case.n):
        if k == case.ref:
            continue
        est = mtb_shift(r.gray8[case.ref], r.gray8[k]) * r.cell
        tru = case.true_warp(k)[:, :2] @ c + case.true_warp(k)[:, 2] - c
        errs.append(float(np.hypot(*(est - tru))))
    return {"shift": errs, "s": time.perf_counter() - t}


def hdrmerge_psnr(cfa: np.ndarray, truths: list, peak: float, measurable) -> float:
    """HDRMerge's output (CFA) against the frames' truths (2x2-cell means), located by phase
    correlation (integer cells), the best frame kept; over the cells ``measurable(truth)``
    marks in every pixel (as ours) and where its output is positive (its crop)."""
    from hdrmerge_cli.core.cfa import mosaic

    h, w = (cfa.shape[0] // 2) * 2, (cfa.shape[1] // 2) * 2

    def cells(a):
        return a[:h, :w].reshape(h // 2, 2, w // 2, 2).mean(axis=(1, 3))

    out = cells(np.nan_to_num(cfa.astype(np.float64)))
    best = -np.inf
    m = 8  # cells
    for truth in truths:
        tc = cells(mosaic(truth, "RGGB"))
        lo = np.log(np.maximum(out, 1e-3 * tc.min()))
        lt = np.log(tc)
        win = cv2.createHanningWindow(lt.shape[::-1], cv2.CV_64F)
        (dx, dy), _ = cv2.phaseCorrelate(lt - lt.mean(), lo - lo.mean(), win)
        dx, dy = int(round(dx)), int(round(dy))
        # out(x + d) ~ truth(x)
        H, W = lt.shape
        ys, xs = slice(max(0, -dy) + m, min(H, H - dy) - m), slice(max(0, -dx) + m, min(W, W - dx) - m)
        a = lo[ys.start + dy:ys.stop + dy, xs.start + dx:xs.stop + dx]
        b = lt[ys, xs]
        keep = (measurable(truth)[:h, :w].reshape(h // 2, 2, w // 2, 2).all(axis=(1, 3))[ys, xs]
                & (out[ys.start + dy:ys.stop + dy, xs.start + dx:xs.stop + dx] > 0))
        if keep.sum() < 100:
            continue
        d = a[keep] - b[keep]
        d -= np.median(d)
        best = max(best, float(20 * np.log10(peak / np.sqrt(np.mean(d * d)))))
    return best if np.isfinite(best) else float("nan")


def run_hdrmerge(paths, out: Path) -> tuple[np.ndarray, float, float]:
    from benchmarks.cli_defaults import read_float_dng
    from benchmarks.peers import QT

    _, wall, mib = measured(["hdrmerge", "-b", "32", "-o", out, *paths], out.parent, env=QT)
    return read_float_dng(out)[0], wall, mib


def merge_options(r: Rendered) -> list[str]:
    """The merge options of a rendered bracket: its reference frame's time; RAW scored per CFA
    site (``--cfa``), 8-bit through its known response."""
    return ["--reference", repr(float(r.times[r.case.ref]))] + (["--cfa"] if r.case.fmt == "raw" else
                                                                ["--crf", f"gamma:{GAMMA:g}"])


def run_case(case: Case, work: Path, peers: bool = True) -> dict:
    folder = work / f"case{case.index:02d}"
    r = render(case, folder)
    extra = merge_options(r)
    res = {"case": case}
    runs = {}
    runs["static_plain"] = merge(r.static, folder / "static" / "plain.exr", "off", "off", extra)
    runs["static_auto"] = merge(r.static, folder / "static" / "auto.exr", "auto", "auto", extra)
    runs["auto"] = merge(r.moving, folder / "moving" / "auto.exr", "auto", "auto", [*extra, "--extra-channels", "ghost"])
    if runs["auto"].get("alignment", {}).get("motion") == "similarity":  # the same run: reuse it
        runs["similarity"] = runs["auto"]
        res["similarity_is_auto"] = True
    else:
        runs["similarity"] = merge(r.moving, folder / "moving" / "similarity.exr", "similarity", "auto", extra)
    true_rgb = merge_true_warps(r.moving, folder / "moving" / "true.exr", [case.true_warp(k) for k in range(case.n)],
                                extra)
    g = case.ghost_frame
    oracle_in = [r.moving[g]] if g == case.ref else [p for k, p in enumerate(r.static) if k != g]
    try:
        runs["oracle"] = merge(oracle_in, folder / "oracle.exr", "off", "off", extra)
    except RuntimeError as exc:
        res["oracle_error"] = str(exc)

    region = r.covered
    lt = np.log(r.truth_static.mean(axis=-1)[region])
    peak = float(lt.max() - lt.min())
    near = cv2.dilate(r.footprint.astype(np.uint8), np.ones((17, 17), np.uint8)).astype(bool)
    away = region & ~near
    e_static = log_error(runs["static_plain"]["_rgb"], r.truth_static, region)
    res["psnr_static"] = psnr(e_static, region, peak)
    res["psnr_static_away"] = psnr(e_static, away, peak)
    e = log_error(runs["static_auto"]["_rgb"], r.truth_static, region)
    res["psnr_static_auto"] = psnr(e, region, peak)
    res["static_rejected"] = max(runs["static_auto"].get("deghost", {}).get("rejected_fraction", [float("nan")]))
    res["static_deghosted"] = runs["static_auto"].get("deghost", {}).get("applied")
    res["static_aligned"] = runs["static_auto"].get("alignment", {}).get("applied")
    for name in ("static_plain", "static_auto", "auto", "similarity"):
        res[f"s_{name}"], res[f"mib_{name}"] = runs[name]["_s"], runs[name]["_mib"]

    e_oracle = log_error(runs["oracle"]["_rgb"], r.truth, region & ~r.footprint) if "oracle" in runs else None
    f0 = r.footprint & region & (np.abs(r.contrast) >= 0.2)
    res["ghost_f0"] = int(f0.sum())
    if e_oracle is not None:
        f = f0 & (np.abs(e_oracle) <= np.minimum(np.abs(r.contrast) / 2, ORACLE_MAX))
        res["ghost_f"] = int(f.sum())
        # (+ 1e-4: a merge that reads a pixel as the oracle does must not fail it on round-off,
        # e.g. a dark ghost at black in a RAW reference, where much of F sits at the oracle's
        # very error plus a few 1e-6)
        tol = max(0.05, float(np.percentile(np.abs(e_oracle[f]), 99))) + 1e-4 if f.any() else float("nan")
        res["ghost_tol"] = tol
    err = log_error(true_rgb, r.truth, region & ~r.footprint)
    res["psnr_true"], res["psnr_true_away"] = psnr(err, region, peak), psnr(err, away, peak)
    for name in ("auto", "similarity"):
        s = runs[name]
        err = log_error(s["_rgb"], r.truth, region & ~r.footprint)
        res[f"psnr_{name}"] = psnr(err, region, peak)
        res[f"psnr_{name}_away"] = psnr(err, away, peak)
        al = s.get("alignment")
        res[f"aligned_{name}"] = al.get("applied") if al else None
        res[f"motion_{name}"] = al.get("motion") if al else None
        res[f"warp_{name}"] = warp_errors(case, al["warps"]) if al and "warps" in al else None
        res[f"rejected_{name}"] = s.get("deghost", {}).get("rejected_fraction")
        res[f"deghosted_{name}"] = s.get("deghost", {}).get("applied")
        if e_oracle is not None and res["ghost_f"]:
            res[f"ghost_removed_{name}"] = float(np.mean(np.abs(err[f]) <= res["ghost_tol"]))
            if "_ghost" in s:  # detection alone: some frame dropped there (the ghost's, or for a ghost in
                # the reference the others)
                res[f"ghost_dropped_{name}"] = float(np.mean(s["_ghost"][f] > 0))
    res["mtb"] = score_mtb(r)
    if peers and case.fmt == "raw" and shutil.which("hdrmerge"):
        try:
            mov, s_mov, mib_mov = run_hdrmerge(r.moving, folder / "moving" / "hdrmerge.dng")
            sta, _, _ = run_hdrmerge(r.static, folder / "static" / "hdrmerge.dng")
            truths = [np.maximum(t, 1e-6) for t in r.frame_truths]
            res["hdrmerge"] = {"psnr": hdrmerge_psnr(mov, truths, peak, r.measurable),
                               "psnr_static": hdrmerge_psnr(sta, [r.truth_static], peak, r.measurable),
                               "s": s_mov, "mib": mib_mov}
        except Exception as exc:  # noqa: BLE001 - a failing peer is reported, not fatal
            res["hdrmerge_error"] = str(exc)[:200]
    shutil.rmtree(folder, ignore_errors=True)
    return res


def run_large(index: int, width: int, height: int, work: Path) -> dict:
    """One moving bracket at a cost target's size: plain and auto/auto, time, peak RSS and the
    alignment's error (the cost targets are stated at 6 and 24 MP)."""
    case = draw_case(index, width, height, scene_names())
    folder = work / f"large{index}"
    r = render(case, folder)
    extra = merge_options(r)
    plains, autos = [], []
    for _ in range(LARGE_REPEATS):  # alternating, so a passing load slows both
        plains.append(merge(r.moving, folder / "plain.exr", "off", "off", extra))
        autos.append(merge(r.moving, folder / "auto.exr", "auto", "auto", extra))
    auto = autos[-1]
    w = warp_errors(case, auto["alignment"]["warps"])
    shutil.rmtree(folder, ignore_errors=True)

    def median(runs, key):
        return float(np.median([x[key] for x in runs]))

    return {"case": case, "s_plain": median(plains, "_s"), "mib_plain": median(plains, "_mib"),
            "s_auto": median(autos, "_s"), "mib_auto": median(autos, "_mib"), "shift": max(w["shift"]),
            "corner": max(w["corner"]), "rot": max(w["rot"]), "stages": auto.get("timing_seconds", {})}


# --- real brackets -----------------------------------------------------------------------


def real_brackets(names=None) -> list[str]:
    root = DATA / "brackets"
    if not root.is_dir():
        return []
    return sorted(p.name for p in root.iterdir() if p.is_dir() and (names is None or p.name in names))


def run_real(name: str, work: Path) -> dict:
    folder = DATA / "brackets" / name
    paths = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".tif", ".tiff", ".png"))
    out = work / name
    out.mkdir()
    res = {"name": name, "frames": len(paths)}
    plain = merge(paths, out / "plain.exr", "off", "off", ["--crf", "srgb"])
    auto = merge(paths, out / "auto.exr", "auto", "auto", ["--crf", "srgb"])
    res.update(width=plain["width"], height=plain["height"], s_plain=plain["_s"], mib_plain=plain["_mib"],
               s_auto=auto["_s"], mib_auto=auto["_mib"])
    al, dg = auto.get("alignment", {}), auto.get("deghost", {})
    res["aligned"] = al.get("applied")
    res["displacement"] = max(al.get("largest_displacement_px", [float("nan")]))
    res["rotation"] = max((abs(v) for v in al.get("rotation_deg", [])), default=None)
    res["rejected"] = max(dg.get("rejected_fraction", [float("nan")]))
    res["deghosted"] = dg.get("applied")
    if name not in HANDHELD + GHOST + LIGHTING:  # a still bracket again, through its own response
        # (estimate-crf, as merge's "sRGB assumed" warning advises): what is left of the false
        # rejections without the assumed response's error
        cmd = [cli(), "estimate-crf", *paths, "-o", out / "crf.json", "-q"]
        measured(cmd, out)
        own = merge(paths, out / "own.exr", "auto", "auto", ["--crf", str(out / "crf.json")])
        res["rejected_own"] = max(own.get("deghost", {}).get("rejected_fraction", [float("nan")]))
    # AlignMTB on the frames in merge's (exposure) order, against the middle one
    order = [f["path"] for f in auto["frames"]]
    grays = [cv2.imread(p, cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION) for p in order]
    ref = len(order) // 2
    t = time.perf_counter()
    res["mtb"] = max(float(np.hypot(*mtb_shift(grays[ref], g))) for g in grays)
    res["mtb_s"] = time.perf_counter() - t
    shutil.rmtree(out, ignore_errors=True)
    return res


# --- report --------------------------------------------------------------------------------


def _f(x, fmt="{:.2f}", none="-"):
    return none if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def _pct(a) -> str:
    a = [x for x in a if x is not None]
    return f"{100 * np.mean(a):.0f} % ({int(np.sum(a))}/{len(a)})" if a else "-"


def _targets_section(ok: list[dict], real: list[dict], large) -> list[str]:
    """The table of the targets: each measured over the cases that ran."""
    lines = []
    lines += ["## Against the targets", "",
              "| target | measured (`--align auto --deghost auto`) | `--align similarity --deghost auto` |",
              "|---|---|---|"]

    def hit(name, key, sub, tol, frames=None):
        vals = []
        for r in ok:
            w = r.get(f"warp_{name}")
            if w is None:
                vals.append(False)
                continue
            v = w[sub] if frames is None else [w[sub][frames]]
            vals.append(max(v) <= tol)
        return _pct(vals)

    lines.append(f"| shift (centre) within {SHIFT_TOL} px, every frame, in >= 99 % of cases | "
                 f"{hit('auto', 'warp', 'shift', SHIFT_TOL)} | {hit('similarity', 'warp', 'shift', SHIFT_TOL)} |")
    lines.append(f"| ... the dark short frame (frame 0) alone | {hit('auto', 'warp', 'shift', SHIFT_TOL, 0)} | "
                 f"{hit('similarity', 'warp', 'shift', SHIFT_TOL, 0)} |")
    lines.append(f"| rotation within {ROT_TOL} deg, every frame | {hit('auto', 'warp', 'rot', ROT_TOL)} | "
                 f"{hit('similarity', 'warp', 'rot', ROT_TOL)} |")
    lines.append(f"| every corner within {SHIFT_TOL} px (shift and rotation together) | "
                 f"{hit('auto', 'warp', 'corner', SHIFT_TOL)} | {hit('similarity', 'warp', 'corner', SHIFT_TOL)} |")
    d = {n: [r[f"psnr_{n}"] - r["psnr_static"] for r in ok] for n in ("auto", "similarity")}
    da = {n: [r[f"psnr_{n}_away"] - r["psnr_static_away"] for r in ok] for n in ("auto", "similarity")}
    lines.append(f"| merged within {PSNR_TOL} dB of the static bracket (dPSNR >= -{PSNR_TOL}): cases; median dPSNR | "
                 + " | ".join(f"{_pct([x >= -PSNR_TOL for x in d[n]])}; {np.median(d[n]):+.2f} dB" for n in d) + " |")
    lines.append("| ... away from the ghost (footprint + 8 px excluded) | "
                 + " | ".join(f"{_pct([x >= -PSNR_TOL for x in da[n]])}; {np.median(da[n]):+.2f} dB" for n in da) + " |")
    for fmt in ("raw", "8bit"):  # the registration's share of the loss: the same merge with the true warps
        rs = [r for r in ok if r["case"].fmt == fmt and "psnr_true_away" in r]
        if rs:
            est = [r["psnr_auto_away"] - r["psnr_static_away"] for r in rs]
            tru = [r["psnr_true_away"] - r["psnr_static_away"] for r in rs]
            lines.append(f"| ... away from the ghost, {fmt}: estimated warps; the true warps (oracle registration) | "
                         f"{_pct([x >= -PSNR_TOL for x in est])}; {np.median(est):+.2f} dB | "
                         f"true warps: {_pct([x >= -PSNR_TOL for x in tru])}; {np.median(tru):+.2f} dB |")
    gr = {n: [r.get(f"ghost_removed_{n}") for r in ok if r.get(f"ghost_removed_{n}") is not None]
          for n in ("auto", "similarity")}
    lines.append(f"| >= {GHOST_TARGET:.0%} of ghost pixels removed: cases; mean removed | "
                 + " | ".join(f"{_pct([x >= GHOST_TARGET for x in gr[n]])}; {100 * np.mean(gr[n]):.1f} %"
                              if gr[n] else "-" for n in gr) + " |")
    dropped = [r["ghost_dropped_auto"] for r in ok if r.get("ghost_dropped_auto") is not None]
    if dropped:  # removal = detection and a reconstruction within the oracle's tolerance; detection alone
        lines.append(f"| ... detection alone: >= {GHOST_TARGET:.0%} of those pixels have a frame dropped "
                     f"(`--extra-channels ghost`): cases; mean | {_pct([x >= GHOST_TARGET for x in dropped])}; "
                     f"{100 * np.mean(dropped):.1f} % | |")
    rej = [r["static_rejected"] for r in ok]
    lines.append(f"| static twins: <= {REJECT_TOL:.1%} of cells rejected: cases; worst | "
                 f"{_pct([x <= REJECT_TOL for x in rej])}; {100 * max(rej):.2f} % | |")
    lines.append("| static twins: PSNR cost of auto/auto over plain (median, worst) | "
                 f"{np.median([r['psnr_static_auto'] - r['psnr_static'] for r in ok]):+.3f} dB, "
                 f"{min(r['psnr_static_auto'] - r['psnr_static'] for r in ok):+.3f} dB | |")
    stat_real = [x for x in real if x["name"] not in HANDHELD + GHOST + LIGHTING and "error" not in x]
    if stat_real:
        lines.append(f"| real static brackets: <= {REJECT_TOL:.1%} of cells rejected | "
                     f"{_pct([x['rejected'] <= REJECT_TOL for x in stat_real])}; worst "
                     f"{100 * max(x['rejected'] for x in stat_real):.2f} % | |")
        own = [x["rejected_own"] for x in stat_real if "rejected_own" in x]
        if own:
            lines.append(f"| ... each through its own response (`estimate-crf`, not sRGB) | "
                         f"{_pct([x <= REJECT_TOL for x in own])}; worst {100 * max(own):.2f} % | |")
    tr = [r["s_auto"] / r["s_static_plain"] for r in ok] + [x["s_auto"] / x["s_plain"] for x in real if "error" not in x]
    mr = [r["mib_auto"] / r["mib_static_plain"] for r in ok] + [x["mib_auto"] / x["mib_plain"] for x in real
                                                                if "error" not in x]
    lines.append(f"| time of auto/auto <= {TIME_RATIO:g}x plain (synthetic + real): brackets; median, worst | "
                 f"{_pct([x <= TIME_RATIO for x in tr])}; {np.median(tr):.2f}x, {max(tr):.2f}x | |")
    lines.append(f"| peak RSS of auto/auto <= {MEM_RATIO:g}x plain: brackets; median, worst | "
                 f"{_pct([x <= MEM_RATIO for x in mr])}; {np.nanmedian(mr):.2f}x, {np.nanmax(mr):.2f}x | |")
    big = [x for x in large if "error" not in x]
    if big:
        lines.append(f"| ... at 6 and 24 MP (one moving bracket each): time; peak RSS | "
                     + "; ".join(f"{x['case'].width * x['case'].height / 1e6:.0f} MP {x['case'].fmt} "
                                 f"{x['s_auto'] / x['s_plain']:.2f}x, {x['mib_auto'] / x['mib_plain']:.2f}x" for x in big)
                     + " | |")
    lines += ["", "Shift/rotation errors are of the warps merge reports (`alignment.warps` in `--json`), whether "
              "or not `auto` decided to apply them; 'aligned' below says whether it did.", ""]

    return lines


def _alignment_section(ok: list[dict]) -> list[str]:
    """Alignment errors (the worst frame of a case), ours and the peers'."""
    lines = []
    lines += ["## Alignment error (worst frame of a case), ours and the peers", "",
              "| method | cases | shift px median | shift px p90 | shift px worst | rotation deg median | worst | "
              "shift <= 0.2 px | shift <= 1 px |", "|---|---|---|---|---|---|---|---|---|"]
    for name, label in (("auto", "hdrmerge-cli --align auto"), ("similarity", "hdrmerge-cli --align similarity")):
        ws = [r[f"warp_{name}"] for r in ok if r.get(f"warp_{name}")]
        if not ws:
            lines.append(f"| {label} | 0 | | | | | | | |")
            continue
        s = np.array([max(w["shift"]) for w in ws])
        rot = np.array([max(w["rot"]) for w in ws])
        lines.append(f"| {label} | {len(ws)} | {np.median(s):.3f} | {np.percentile(s, 90):.3f} | {s.max():.2f} | "
                     f"{np.median(rot):.3f} | {rot.max():.3f} | {np.mean(s <= 0.2):.0%} | {np.mean(s <= 1):.0%} |")
    s = np.array([max(r["mtb"]["shift"]) for r in ok])
    lines.append(f"| OpenCV AlignMTB (translation, integer px) | {len(s)} | {np.median(s):.3f} | "
                 f"{np.percentile(s, 90):.3f} | {s.max():.2f} | - | - | {np.mean(s <= 0.2):.0%} | {np.mean(s <= 1):.0%} |")
    return lines


def _psnr_section(ok: list[dict]) -> list[str]:
    """PSNR against the static twin, per method and format (HDRMerge on RAW)."""
    lines = []
    hm = [r["hdrmerge"] for r in ok if "hdrmerge" in r and np.isfinite(r["hdrmerge"]["psnr"] - r["hdrmerge"]["psnr_static"])]
    raw_rows = [r for r in ok if r["case"].fmt == "raw"]
    lines += ["", "## PSNR against the static twin (RAW cases: HDRMerge alongside)", "",
              "| method | cases | dPSNR median dB | dPSNR worst dB | mean s | mean peak MiB |", "|---|---|---|---|---|---|"]
    for name, label in (("auto", "hdrmerge-cli --align auto --deghost auto"),
                        ("similarity", "hdrmerge-cli --align similarity --deghost auto")):
        for fmt in ("raw", "8bit"):
            rs = [r for r in ok if r["case"].fmt == fmt]
            if rs:
                dd = [r[f"psnr_{name}"] - r["psnr_static"] for r in rs]
                lines.append(f"| {label} ({fmt}) | {len(rs)} | {np.median(dd):+.2f} | {min(dd):+.2f} | "
                             f"{np.mean([r[f's_{name}'] for r in rs]):.2f} | "
                             f"{np.mean([r[f'mib_{name}'] for r in rs]):.0f} |")
    if hm:
        dd = [h["psnr"] - h["psnr_static"] for h in hm]
        lines.append(f"| HDRMerge 0.5 defaults (raw; its own 2x2-cell metric) | {len(hm)} | {np.median(dd):+.2f} | "
                     f"{min(dd):+.2f} | {np.mean([h['s'] for h in hm]):.2f} | {np.mean([h['mib'] for h in hm]):.0f} |")
    elif raw_rows:
        why = next((r["hdrmerge_error"] for r in raw_rows if "hdrmerge_error" in r),
                   "not installed (apt-get install hdrmerge)" if not shutil.which("hdrmerge") else "not run")
        lines.append(f"| HDRMerge | 0 | {why} | | | |")

    return lines


def _cases_section(rows: list[dict]) -> list[str]:
    """One table row per random case."""
    lines = []
    lines += ["", "## Every case", "",
              "| # | fmt | N | EV step | short frame peak | scene | ghost frame (ref) / area | max shift px / rot deg | "
              "auto: aligned, shift err px, rot err deg, corner err px | similarity: shift err, rot err, corner err | "
              "AlignMTB shift err | PSNR static / auto / similarity dB | PSNR away from the ghost static / auto | ghost removed auto / sim (F px; a frame dropped there, auto) | "
              "rejected: static twin / auto | s plain / auto | MiB plain / auto | HDRMerge PSNR static / moving (2x2 cells) |",
              "|" + "---|" * 18]
    for r in rows:
        c = r["case"]
        if "error" in r:
            lines.append(f"| {c.index} | {c.fmt} | {c.n} | {c.step:.2f} | {c.dark:.2f} | {c.scene} | failed: {r['error']} |"
                         + " |" * 12)
            continue
        mx = max(np.hypot(*s) for s in c.shift)
        wa, ws = r.get("warp_auto"), r.get("warp_similarity")
        hmr = r.get("hdrmerge")
        lines.append(
            f"| {c.index} | {c.fmt} | {c.n} | {c.step:.2f} | {c.dark:.2f} | {c.scene.removeprefix('ScanLines_')} | "
            f"{c.ghost_frame} ({c.ref}) / {100 * c.ghost['area']:.1f} % | {mx:.1f} / {max(abs(v) for v in c.rot):.2f} | "
            + (f"{r['aligned_auto']}, {max(wa['shift']):.3f}, {max(wa['rot']):.3f}, {max(wa['corner']):.2f}" if wa else "-")
            + " | " + (f"{max(ws['shift']):.3f}, {max(ws['rot']):.3f}, {max(ws['corner']):.2f}" if ws else "-")
            + f" | {max(r['mtb']['shift']):.2f} | {r['psnr_static']:.2f} / {r['psnr_auto']:.2f} / {r['psnr_similarity']:.2f}"
            + f" | {r['psnr_static_away']:.2f} / {r['psnr_auto_away']:.2f}"
            + f" | {_f(r.get('ghost_removed_auto'), '{:.1%}')} / {_f(r.get('ghost_removed_similarity'), '{:.1%}')} "
              f"({r.get('ghost_f', '-')}; dropped {_f(r.get('ghost_dropped_auto'), '{:.0%}')})"
            + f" | {100 * r['static_rejected']:.2f} % / {100 * max(r['rejected_auto'] or [float('nan')]):.2f} %"
            + f" | {r['s_static_plain']:.1f} / {r['s_auto']:.1f} | {r['mib_static_plain']:.0f} / {r['mib_auto']:.0f}"
            + (f" | {hmr['psnr_static']:.2f} / {hmr['psnr']:.2f} |" if hmr else " | - |"))
    return lines


def _large_section(large) -> list[str]:
    """Time and memory of one moving bracket at each large size."""
    lines = []
    lines += ["", "## Cost at 6 and 24 MP (one moving bracket each, a fresh render; no peers)", "",
              f"| case | fmt | size | frames | s plain / auto (ratio; medians of {LARGE_REPEATS}, alternating) | "
              "MiB plain / auto (ratio) | shift / corner err px, "
              "rot err deg | auto's stages s |", "|" + "---|" * 8]
    for x in large:
        c = x["case"]
        if "error" in x:
            lines.append(f"| {c.index} | {c.fmt} | {c.width} x {c.height} | failed: {x['error']} |" + " |" * 4)
            continue
        st = ", ".join(f"{k} {v:.2f}" for k, v in x["stages"].items() if v >= 0.05)
        lines.append(f"| {c.index} | {c.fmt} | {c.width} x {c.height} | {c.n} | {x['s_plain']:.1f} / "
                     f"{x['s_auto']:.1f} ({x['s_auto'] / x['s_plain']:.2f}x) | {x['mib_plain']:.0f} / "
                     f"{x['mib_auto']:.0f} ({x['mib_auto'] / x['mib_plain']:.2f}x) | {x['shift']:.3f} / "
                     f"{x['corner']:.2f}, {x['rot']:.4f} | {st} |")
    return lines


def _real_section(real: list[dict]) -> list[str]:
    """One table row per real bracket."""
    lines = []
    lines += ["", "## Real brackets (`--crf srgb`, no truth)", "",
              "| bracket | kind | frames | size | aligned | largest displacement px | rotation deg | AlignMTB largest "
              "shift px | cells rejected (worst frame); through its own response | deghosted | s plain / auto | "
              "MiB plain / auto |",
              "|" + "---|" * 12]
    for x in real:
        kind = ("hand-held" if x["name"] in HANDHELD else "ghost" if x["name"] in GHOST
                else "lamps switched off" if x["name"] in LIGHTING else "static")
        if "error" in x:
            lines.append(f"| {x['name']} | {kind} | failed: {x['error']} |" + " |" * 9)
            continue
        lines.append(f"| {x['name']} | {kind} | {x['frames']} | {x['width']} x {x['height']} | {x['aligned']} | "
                     f"{x['displacement']:.2f} | {_f(x['rotation'], '{:.3f}')} | {x['mtb']:.1f} | "
                     f"{100 * x['rejected']:.2f} %"
                     + (f"; {100 * x['rejected_own']:.2f} %" if "rejected_own" in x else "")
                     + f" | {x['deghosted']} | {x['s_plain']:.1f} / {x['s_auto']:.1f} | "
                     f"{x['mib_plain']:.0f} / {x['mib_auto']:.0f} |")
    return lines


def report(rows: list[dict], real: list[dict], notes: list[str], quick: bool, seconds: float, width: int,
           height: int, large: list[dict] = ()) -> list[str]:
    ok = [r for r in rows if "error" not in r]
    lines = ["# Motion: alignment and ghost removal on randomised brackets", "",
             f"`python -m benchmarks.motion{' --quick' if quick else ''}` at revision {revision()}; {seconds:.0f} s; "
             f"{len(rows)} random cases ({sum(r['case'].fmt == 'raw' for r in rows)} RAW, "
             f"{sum(r['case'].fmt == '8bit' for r in rows)} 8-bit), {width} x {height} px, seeds {SEED}+i.  "
             "Protocol in the module docstring: shifts +-20 px and rotations +-2 deg of every non-reference frame, "
             "1-3 EV steps with a dark short frame, one ghost of random size/brightness in a random frame, real HDR "
             "scenes (../shared/data/hdr).", ""]
    lines += notes + ([""] if notes else [])

    lines += _targets_section(ok, real, large)
    lines += _alignment_section(ok)
    lines += _psnr_section(ok)
    lines += _cases_section(rows)
    if large:
        lines += _large_section(large)
    if real:
        lines += _real_section(real)
    lines += ["", "Columns: 'short frame peak' = the fraction of saturation the scene's 99.9th percentile reaches in "
              "the shortest frame; errors are the worst non-reference frame's; 'ghost removed' over F pixels (see the "
              "docstring; '-' when the oracle leaves none); 'rejected' = largest fraction of a frame's cells "
              "deghosting flags; times and peak RSS are of the whole command."]
    return lines


def main(quick: bool = False, cases: int | None = None, size: tuple[int, int] | None = None,
         real: bool = True, peers: bool = True, out: Path | None = None) -> str:
    """Run the benchmark and write its table (``out``: default results/motion[_quick].md)."""
    name = "motion_quick.md" if quick else "motion.md"
    out = out or RESULTS / name
    if not (DATA / "hdr").is_dir():
        return write_result(out, ["# Motion benchmark", "", f"skipped: {DATA / 'hdr'} is missing"])
    n_cases = cases if cases is not None else (6 if quick else 32)
    width, height = size or ((400, 300) if quick else (1000, 700))
    names = scene_names()
    notes = []
    if not Path("/usr/bin/time").exists():
        notes.append("Peak RSS from resource.getrusage(RUSAGE_CHILDREN) (no /usr/bin/time).")
    if peers and not shutil.which("hdrmerge"):
        notes.append("HDRMerge not installed (apt-get install hdrmerge): its column is empty.")
    t_start = time.perf_counter()
    rows, reals = [], []
    with tempfile.TemporaryDirectory(prefix="motion.") as tmp:
        tmp = Path(tmp)
        for i in range(n_cases):
            case = draw_case(i, width, height, names)
            try:
                rows.append(run_case(case, tmp, peers))
            except Exception as exc:  # noqa: BLE001 - reported in the table
                rows.append({"case": case, "error": str(exc)[:200]})
            print(f"[motion] case {i}: {time.perf_counter() - t_start:.0f} s", file=sys.stderr, flush=True)
        large = []
        for index, w, h in (() if quick else LARGE):
            try:
                large.append(run_large(index, w, h, tmp))
            except Exception as exc:  # noqa: BLE001 - reported in the table
                large.append({"case": draw_case(index, w, h, names), "error": str(exc)[:200]})
            print(f"[motion] {w} x {h}: {time.perf_counter() - t_start:.0f} s", file=sys.stderr, flush=True)
        if real:
            for b in real_brackets(None if not quick else ("stack_jpg", "stack_handheld_jpg", "stack_ghost_jpg")):
                try:
                    reals.append(run_real(b, tmp))
                except Exception as exc:  # noqa: BLE001
                    reals.append({"name": b, "error": str(exc)[:200]})
                print(f"[motion] {b}: {time.perf_counter() - t_start:.0f} s", file=sys.stderr, flush=True)
    if not any("error" not in r for r in rows):
        return write_result(out, ["# Motion benchmark", "", "every case failed:", ""]
                            + [f"- case {r['case'].index}: {r['error']}" for r in rows])
    return write_result(out, report(rows, reals, notes, quick, time.perf_counter() - t_start, width, height, large))


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="6 cases of 400 x 300 px, the three small real brackets")
    ap.add_argument("--cases", type=int, help="number of random cases (default 32, quick 6)")
    print(main(ap.parse_args().quick, ap.parse_args().cases))
