"""What the command line gives with its default options, against the Cramer-Rao bound and
peer programs, on simulated brackets with known ground truth.

Every bracket is rendered by ``hdrmerge-cli simulate`` (the sensor model (16)-(18), seeded)
from two of the shared HDR scenes (``../shared/data/hdr``: ScanLines_Desk, ~17 stops, and
ScanLines_MtTamWest, ~11 stops, between the 0.5th and 99.95th percentiles), area-resized to
~0.4 MP and normalised so that the brightest 0.05 % reach 90 % of saturation in the shortest
frame.  4 frames 2 EV apart, ``--times 1/1024,1/256,1/64,1/16``; a 12-bit linear A/D converter
with black level 0 (so that the bound below, whose codes clip at 0 and full scale, is the
exact bound of the files) and the three (sqrt(alpha), sigma_o) operating points of
``benchmarks.accuracy.SHORT_SWEEP`` in 8-bit code units of the linear signal, scaled by
4095/255 to the 12-bit converter: (4, 0.5) photon-noise limited, (1, 2) moderate, (0.25, 16)
read-noise limited (``--alpha (g 4095/255)^2 --sigma-o2 (s 4095/255)^2 - 1/12``).

A. RAW: 12-bit DNG (RGGB).  ``hdrmerge-cli merge FRAMES --cfa -o out.exr --reference T``
   (``T`` = simulation.json's ``reference_exposure``; nothing else: the defaults, which
   measure the noise on the bracket), then ``--weights triangle``, ``--weights uniform``,
   ``--weights probabilistic`` and ``--estimator log`` one at a time, and the defaults with
   the true ``--noise sigma_o2=sigma_o2_total,alpha=alpha`` (12-bit codes; does measuring the
   noise on the bracket cost anything?).  Peer: HDRMerge 0.5, ``hdrmerge -b 32 -o out.dng
   FRAMES`` (its defaults: auto-alignment, crop, mask blur 3; ``QT_QPA_PLATFORM=offscreen``),
   and with ``--no-align``: its alignment moves these static frames by up to hundreds of
   pixels on some brackets and crops (such an output is reported, not scored).  Its
   floating-point DNG (deflate, floating-point predictor) is read by :func:`read_float_dng`
   below: LibRaw (rawpy 0.28) refuses it ("Corrupted data") and tifffile is not a
   dependency.  Truth: ``truth.exr`` mosaicked to RGGB.
B. 8-bit: lossless 8-bit TIFF through ``--crf gamma:2.5`` (codes = x^0.4 of the 12-bit ADC
   output).  ``hdrmerge-cli merge FRAMES --crf gamma:2.5 -o out.exr`` (defaults), then
   ``--weights probabilistic``, ``--estimator ml``, ``--estimator log``, ``--estimator ml
   --weights uniform``, and each of the five again with the true noise ``--noise
   sigma_o2=S,alpha=A`` on the linearised 8-bit signal (``S = sigma_o2_total / (4095/255)^2``,
   ``A = alpha / (4095/255)^2``); and the defaults with that noise 10 % low and 10 % high
   (the estimator the defaults pick when the noise model is off by 10 %).
   Peers, each given the true response x^2.5 (exposure times from simulation.json):
   - pfstools 2.2: ``pfsinhdrgen`` (hdrgen lines ``file 1/t 1 100 0``) ``| pfshdrcalibrate -f
     true.m | pfsout out.exr``: ``-f`` turns self-calibration off and merges with that
     response (pfstools 2.2 merges with its "Poisson photon noise estimator", Hanji et al.
     2020); ``true.m`` holds the IR/IG/IB matrices ``log10(I) | z | I`` with ``I = (z/255)^2.5``
     and a weight matrix W, which the file format requires and that merge ignores (checked:
     identical output for three different W); ``-r gamma`` is a fixed curve of its own.
   - Luminance HDR 2.6: ``luminance-hdr-cli -e log2(t),... --hdrModel debevec|robertson
     --hdrResponseCurve from_file --inputCameraResponseCurve true.csv -s out.exr FRAMES``
     (weight triangular, its default), ``true.csv`` its 4096-row format
     ``log10(Ir),Ir,log10(Ig),Ig,log10(Ib),Ib`` with ``I = max((i/4095)^2.5, 1e-10)`` (its
     Debevec merge adds ``w(z) log I(z)`` for every frame, and ``0 x log 0`` turns every pixel
     with a zero code in some frame into its maximum value); ``QT_QPA_PLATFORM=offscreen``.
   - OpenCV ``MergeDebevec`` / ``MergeRobertson`` (in process, frames read by cv2) with the
     response ``max((z/255)^2.5, 1e-6)`` per channel, as in ``benchmarks.accuracy``.

Score, as ``benchmarks.accuracy.evaluate``: PSNR of log E over the samples (CFA sites, or
pixel-channels) whose Cramer-Rao bound on Var[log E] is below 1
(:func:`benchmarks.accuracy.crb_log` with the true sqrt(alpha), sigma_o^2 incl. the 1/12 of
the 12-bit quantisation and full scale, ``"raw"`` or ``"jpeg"``), peak = the log range of those
samples, after one global scale per method (median log ratio; every method, ours included),
samples <= 0 or non-finite and everything below half a 12-bit code of the longest frame set
to that floor; "below CRB" = bound PSNR - PSNR (0 = efficient).  That bound takes (17)'s
Gaussian approximation, whose variance grows with the mean and so claims ~1/2 unit of
Fisher information on log E per photon-limited frame beyond the photon count; the files are
Poisson counts (64 codes per electron at (4, 0.5)), so it is unreachable there (3.1 dB of
Desk (4, 0.5)'s gap).  "below exact CRB" scores against :func:`crb_log_counts`, the bound of
the simulator's own model, over the samples where it is below 1 and (asymptotic score) below
0.1: near 1 the log of any estimate has a heavy lower tail (zero photon counts: the exact
per-sample ML estimate is 5-7 dB further from the bound than ours over CRB in [0.3, 1)).
Wall time: the whole
command (start-up, decoding, writing; the noise estimate of the RAW defaults), OpenCV's the
in-process read + merge.  The table's "settings" column is what our merge resolved its
``auto`` options to (weights/estimator/variance, from the EXR header), and the peers' flags;
the header names the git revision measured (``-dirty``: uncommitted changes in the tree).

    python -m benchmarks.cli_defaults [--quick]   # results/cli_defaults.md (or _quick.md)

Peers: ``apt-get install hdrmerge luminance-hdr pfstools``; a missing one is skipped with a
note in the table (OpenCV is a pip dependency of the project).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from fractions import Fraction
from pathlib import Path

import numpy as np

from benchmarks import revision, write_result
from benchmarks.accuracy import GAMMA, SHORT_SWEEP, crb_log
from benchmarks.peers import QT, read_exr_rgb, run_tool

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
RESULTS = Path(__file__).parent / "results"
SCENES = ("ScanLines_Desk", "ScanLines_MtTamWest")
TIMES = ("1/1024", "1/256", "1/64", "1/16")
BITS = 12
SCALE = (2**BITS - 1) / 255.0  # 8-bit code units -> 12-bit
CRB_MAX = 1.0  # compare samples whose bound on Var[log E] is below this
CRB_TIGHT = 0.1  # ... and, for the asymptotic score, below this (relative sd < ~32 %)

RAW_OURS = {"defaults": [], "--weights triangle": ["--weights", "triangle"],
            "--weights uniform": ["--weights", "uniform"],
            "--weights probabilistic": ["--weights", "probabilistic"], "--estimator log": ["--estimator", "log"]}
LDR_OURS = {"defaults": [], "--weights probabilistic": ["--weights", "probabilistic"],
            "--estimator ml": ["--estimator", "ml"], "--estimator log": ["--estimator", "log"],
            "--estimator ml --weights uniform": ["--estimator", "ml", "--weights", "uniform"]}


def cli() -> str:
    beside = Path(sys.executable).with_name("hdrmerge-cli")
    return str(beside) if beside.exists() else (shutil.which("hdrmerge-cli") or "hdrmerge-cli")


def run(cmd, cwd, stdin=None, stdout=None, env=None) -> float:
    """:func:`benchmarks.peers.run_tool`, timed: wall seconds."""
    t = time.perf_counter()
    run_tool(cmd, cwd, stdin, stdout or subprocess.DEVNULL, env)
    return time.perf_counter() - t


def read_float_dng(path) -> tuple[np.ndarray, tuple[int, int]]:
    """The full-resolution CFA of a floating-point DNG (HDRMerge ``-b 32``): 32-bit float
    samples, deflate-compressed tiles, floating-point predictor (TIFF tech note 3; 34894/34895
    = the DNG 1.4 variants differencing every 2nd/4th byte), in file units; and its
    DefaultCropSize (width, height), smaller than the data when HDRMerge cropped after aligning."""
    b = Path(path).read_bytes()
    bo = "<" if b[:2] == b"II" else ">"
    size = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4, 16: 8}
    fmt = {1: "B", 2: "B", 3: "H", 4: "I", 5: "I", 6: "b", 7: "B", 8: "h", 9: "i", 10: "i", 11: "f", 12: "d",
           13: "I", 16: "Q"}

    def ifd(off):
        tags = {}
        for i in range(struct.unpack_from(bo + "H", b, off)[0]):
            tag, typ, cnt = struct.unpack_from(bo + "HHI", b, off + 2 + 12 * i)
            at = off + 10 + 12 * i
            if size[typ] * cnt > 4:
                at = struct.unpack_from(bo + "I", b, at)[0]
            tags[tag] = struct.unpack_from(bo + fmt[typ] * (cnt * (2 if typ in (5, 10) else 1)), b, at)
        return tags

    root = ifd(struct.unpack_from(bo + "I", b, 4)[0])
    subs = [ifd(o) for o in root.get(330, ())] + [root]
    t = next((s for s in subs if s.get(254, (1,))[0] == 0 and s.get(262, (0,))[0] == 32803), None)
    if t is None or t[258][0] != 32 or t.get(339, (1,))[0] != 3 or t[259][0] not in (8, 32946) or 322 not in t:
        raise ValueError(f"{path}: not a tiled, deflated 32-bit float CFA DNG")
    w, h, tw, th = t[256][0], t[257][0], t[322][0], t[323][0]
    step = {1: 0, 3: 1, 34894: 2, 34895: 4}[t.get(317, (1,))[0]]
    cols = -(-w // tw)
    out = np.zeros((-(-h // th) * th, cols * tw), np.float32)
    for k, (o, n) in enumerate(zip(t[324], t[325])):
        raw = np.frombuffer(zlib.decompress(b[o:o + n]), np.uint8).reshape(th, 4 * tw).copy()
        if step:
            for j in range(step):  # undo the byte differencing, then the byte-plane shuffle (MSB first)
                raw[:, j::step] = np.cumsum(raw[:, j::step], axis=1, dtype=np.uint8)
            vals = raw.reshape(th, 4, tw).transpose(0, 2, 1).copy().view(">f4")[..., 0]
        else:
            vals = raw.view(bo + "f4")
        r, c = divmod(k, cols)
        out[r * th:(r + 1) * th, c * tw:(c + 1) * tw] = vals
    return out[:h, :w], tuple(int(v) for v in t.get(50720, (w, h)))


# --- the exact bound of the simulated files ------------------------------------------------


def crb_log_counts(e: np.ndarray, times, gain: float, sigma_o2: float, full: int, crf=None) -> np.ndarray:
    """Cramer-Rao bound on Var[log E] for the simulator's own model of the files
    (:func:`hdrmerge_cli.core.sensor.expose`, :func:`~hdrmerge_cli.core.sensor.quantise_raw` /
    :func:`~hdrmerge_cli.core.sensor.quantise_crf`): ``y = gain n + N(0, sigma_o2)`` with
    ``n ~ Poisson(t E / gain)`` photo-electrons, rounded and clipped to the ``full``-scale
    linear code, then (``crf``: a :class:`~hdrmerge_cli.core.crf.CRF`) through the response to
    8 bits.  ``sigma_o2`` is the read noise *before* rounding (the rounding is in the bins).

    :func:`benchmarks.accuracy.crb_log` takes the Gaussian approximation of (17),
    ``y ~ N(t E, sigma_o2 + gain t E)``, whose variance grows with the mean and so carries
    information of its own: ~1/2 per photon-limited frame on log E, beside the mean's ``t E /
    gain``.  A Poisson count has no such extra information (its Fisher information on
    log lambda is lambda), so where few electrons are counted (the (4, 0.5) brackets: 64
    codes per electron) that bound is below what any estimator can reach on these files.
    ``e`` in linear code values per second; inverse Fisher information summed over frames."""
    from scipy.stats import norm, poisson

    lam_max = full / gain  # electrons at full scale
    nmax = int(lam_max + 12 * np.sqrt(lam_max) + 60)  # beyond: saturated with certainty
    n = np.arange(nmax + 1, dtype=np.float64)
    edges = np.arange(full + 2) - 0.5
    edges[0], edges[-1] = -np.inf, np.inf
    a = (edges[:, None] - gain * n[None, :]) / np.sqrt(max(sigma_o2, 1e-12))
    cdf, sf = norm.cdf(a), norm.sf(a)
    q = np.maximum(np.where(a[1:] < 0, cdf[1:] - cdf[:-1], sf[:-1] - sf[1:]), 0.0)  # P(code | n)
    if crf is not None:  # 12-bit code -> 8-bit code, as quantise_crf
        from hdrmerge_cli.core.sensor import SensorModel, quantise_crf

        to8 = quantise_crf(np.arange(full + 1, dtype=np.float64)[:, None],
                           SensorModel(bits=int(np.log2(full + 1)), black=0), crf, 8)[:, 0].astype(np.intp)
        q = np.stack([q[to8 == k].sum(0) for k in range(256)])
    info = np.zeros(np.shape(e))
    for t in times:
        lam = np.asarray(e, np.float64) * t / gain
        pmf = poisson.pmf(n[:, None], lam[None, :])
        p = q @ pmf
        dp = q @ (pmf * (n[:, None] - lam[None, :]))  # d P / d log E
        p[-1] += poisson.sf(nmax, lam)  # the rest of the Poisson mass: saturated
        dp[-1] += lam * poisson.pmf(nmax, lam)
        used = p > 1e-12
        info += np.sum(np.where(used, dp * dp / np.where(used, p, 1.0), 0.0), axis=0)
    return 1.0 / np.maximum(info, 1e-300)


# --- brackets ----------------------------------------------------------------------------


def prepare_scene(name: str, mp: float, out: Path) -> Path:
    """The shared scene area-resized to ~``mp`` megapixels, its 99.95th percentile at 1."""
    import cv2

    from hdrmerge_cli.io.images import read_exr, write_exr

    img = np.clip(read_exr(DATA / "hdr" / f"{name}.exr")[0][..., :3].astype(np.float32), 0, None)
    k = np.sqrt(mp * 1e6 / (img.shape[0] * img.shape[1]))
    w, h = int(img.shape[1] * k) // 2 * 2, int(img.shape[0] * k) // 2 * 2
    img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
    img /= np.percentile(img[img > 0], 99.95)
    write_exr(str(out), img, ["R", "G", "B"], {})
    return out


def simulate(scene: Path, fmt: str, gain: float, sigma_o: float, seed: int, out: Path) -> dict:
    alpha = (gain * SCALE) ** 2
    t0 = float(Fraction(TIMES[0]))
    scale = 0.9 * (2**BITS - 1) / np.sqrt(alpha) / t0  # brightest 0.05 % at 90 % of saturation in frame 0
    extra = ["--black", "0"] if fmt == "dng" else ["--crf", f"gamma:{GAMMA:g}", "--out-bits", "8"]
    run([cli(), "simulate", "-o", out, "--scene", scene, "--scale", repr(float(scale)), "--format", fmt, "--bits", BITS,
         "--alpha", repr(alpha), "--sigma-o2", repr(max((sigma_o * SCALE) ** 2 - 1 / 12, 0.0)),
         "--times", ",".join(TIMES), "--seed", seed, "-q", *extra], out.parent)
    meta = json.loads((out / "simulation.json").read_text())
    meta["paths"] = [out / f for f in meta["frames"]]
    return meta


class Bracket:
    """A simulated bracket and its scoring: truth in merge units, the bound, the samples compared.

    Three scores: against the Gaussian-approximation bound (:func:`benchmarks.accuracy.crb_log`,
    the original column) over the samples where it is below ``CRB_MAX``; against the exact
    bound of the files (:func:`crb_log_counts`) over the samples where that is below
    ``CRB_MAX``, and where it is below ``CRB_TIGHT``: near ``Var[log E] = 1`` (relative sd
    ~100 %) the bound on log E is unreachable by any estimator (a count of 0 photons has
    no finite log; the exact ML estimate is several dB further from it than ours there),
    and those samples dominate a mean squared log error."""

    def __init__(self, meta: dict, folder: Path):
        from hdrmerge_cli.core.cfa import mosaic
        from hdrmerge_cli.core.crf import CRF

        self.meta, self.folder = meta, folder
        s = meta["sensor"]
        truth = read_exr_rgb(folder / "truth.exr").astype(np.float64)
        self.truth = mosaic(truth, meta["cfa_pattern"]) if meta["format"] == "dng" else truth
        self.times = np.array(meta["exposure_times"])
        full, t_ref = s["white"] - s["black"], meta["reference_exposure"]
        e = np.maximum(self.truth * full / t_ref, 1e-9).ravel()  # linear code values per second
        grid = np.geomspace(e.min(), e.max(), 300)
        bound = crb_log(grid, self.times, np.sqrt(s["alpha"]), s["sigma_o2_total"], full,
                        "raw" if meta["format"] == "dng" else "jpeg")
        crb = np.exp(np.interp(np.log(e), np.log(grid), np.log(bound)))
        self.ok = crb < CRB_MAX
        self.log_t = np.log(e[self.ok] * t_ref / full)
        self.peak2 = np.ptp(self.log_t) ** 2
        self.crb_db = 10 * np.log10(self.peak2 / np.mean(crb[self.ok]))
        self.floor = 0.5 / full * t_ref / self.times.max()
        exact = crb_log_counts(grid, self.times, np.sqrt(s["alpha"]), s["sigma_o2"], int(full),
                               None if meta["format"] == "dng" else CRF("gamma", GAMMA))
        crb_x = np.exp(np.interp(np.log(e), np.log(grid), np.log(exact)))
        self.exact = []  # (samples, log truth, peak^2, bound dB) for CRB_MAX and CRB_TIGHT
        for limit in (CRB_MAX, CRB_TIGHT):
            ok = crb_x < limit
            log_t = np.log(e[ok] * t_ref / full)
            peak2 = np.ptp(log_t) ** 2 if ok.any() else 1.0
            self.exact.append((ok, log_t, peak2, 10 * np.log10(peak2 / np.mean(crb_x[ok])) if ok.any() else np.nan))

    def _psnr(self, est, ok, log_t, peak2) -> tuple[float, float]:
        est = est.ravel()[ok]
        valid = np.isfinite(est) & (est > 0)
        if not valid.any():
            return np.nan, 1.0
        le = np.log(np.where(valid, est, 1.0))
        le -= np.median(le[valid] - log_t[valid])  # one global scale per method
        le = np.maximum(np.where(valid, le, -np.inf), np.log(self.floor))
        return 10 * np.log10(peak2 / np.mean((le - log_t) ** 2)), 1.0 - valid.mean()

    def score(self, est) -> tuple[float, float, float, float, float]:
        """PSNR (dB), dB below the Gaussian-approximation bound, fraction of compared samples
        <= 0 or non-finite; dB below the exact bound (samples with exact CRB < ``CRB_MAX``),
        and below it over the samples with exact CRB < ``CRB_TIGHT``."""
        est = np.asarray(est, np.float64)
        if est.shape != self.truth.shape:
            raise RuntimeError(f"output is {est.shape[1]}x{est.shape[0]}, not "
                               f"{self.truth.shape[1]}x{self.truth.shape[0]}")
        psnr, invalid = self._psnr(est, self.ok, self.log_t, self.peak2)
        below = [bound_db - self._psnr(est, ok, log_t, peak2)[0] for ok, log_t, peak2, bound_db in self.exact]
        return psnr, self.crb_db - psnr, invalid, *below


# --- methods: each returns (estimate in the truth's layout, seconds, resolved settings) ----


def ours(b: Bracket, flags: list[str], work: Path, name: str):
    out = work / f"{name}.exr"
    if b.meta["format"] == "dng":
        cmd = [cli(), "merge", *b.meta["paths"], "--cfa", "-o", out, "--reference", repr(b.meta["reference_exposure"])]
    else:
        cmd = [cli(), "merge", *b.meta["paths"], "--crf", f"gamma:{GAMMA:g}", "-o", out]
    seconds = run(cmd + flags, work)
    from hdrmerge_cli.io.images import read_exr

    pixels, attrs = read_exr(out)
    how = "/".join(str(attrs.get(f"hdrmerge:{k}", "?")) for k in ("weights", "estimator", "variance"))
    return (pixels[..., 0] if pixels.shape[-1] == 1 else pixels[..., :3]), seconds, how


def hdrmerge(flags: list[str]):
    def method(b: Bracket, work: Path):
        out = work / f"hdrmerge{len(flags)}.dng"
        seconds = run(["hdrmerge", *flags, "-b", "32", "-o", out, *b.meta["paths"]], work, env=QT)
        cfa, crop = read_float_dng(out)
        if crop != cfa.shape[::-1]:
            raise RuntimeError(f"its auto-alignment moved the static frames and cropped the output to "
                               f"{crop[0]}x{crop[1]}")
        return cfa, seconds, " ".join(flags + ["-b", "32"])
    return method


def true_inverse(n: int) -> np.ndarray:
    return (np.arange(n) / (n - 1.0)) ** GAMMA


def pfstools(b: Bracket, work: Path):
    inv = true_inverse(256)
    mats = "".join(
        f"# name: I{c}\n# type: matrix\n# rows: 256\n# columns: 3\n"
        + "".join(f" {np.log10(max(v, 1e-6)):.9e} {z} {v:.9e}\n" for z, v in enumerate(inv)) + "\n\n" for c in "RGB")
    weights = "# name: W\n# type: matrix\n# rows: 256\n# columns: 2\n" + "".join(f" 1 {z}\n" for z in range(256))
    (work / "true.m").write_text(mats + weights)  # W must be present; 2.2's Poisson-noise merge ignores it
    rel = [os.path.relpath(p, work) for p in b.meta["paths"]]
    (work / "stack.hdrgen").write_text("".join(f"{p} {1 / float(t)!r} 1 100 0\n" for p, t in zip(rel, b.times)))
    t = time.perf_counter()
    with open(work / "stack.pfs", "wb") as out:
        run(["pfsinhdrgen", "stack.hdrgen"], work, stdout=out)
    with open(work / "stack.pfs", "rb") as inp, open(work / "hdr.pfs", "wb") as out:
        run(["pfshdrcalibrate", "-f", "true.m"], work, stdin=inp, stdout=out)
    with open(work / "hdr.pfs", "rb") as inp:
        run(["pfsout", "pfs.exr"], work, stdin=inp)
    return read_exr_rgb(work / "pfs.exr"), time.perf_counter() - t, "-f true.m"


def luminance(model: str):
    def method(b: Bracket, work: Path):
        inv = np.maximum(true_inverse(4096), 1e-10)  # its Debevec merge takes log I(z) at every code: no 0
        rows = "".join(",".join([f"{np.log10(v):.9f},{v:.6e}"] * 3) + "\n" for v in inv)
        (work / "true.csv").write_text("log10(Ir),Ir,log10(Ig),Ig,log10(Ib),Ib\n" + rows)
        out = work / f"luminance-{model}.exr"
        seconds = run(["luminance-hdr-cli", "-e", ",".join(f"{np.log2(t):.6f}" for t in b.times), "--hdrModel", model,
                       "--hdrResponseCurve", "from_file", "--inputCameraResponseCurve", "true.csv", "-s", out,
                       *b.meta["paths"]], work, env=QT)
        return read_exr_rgb(out), seconds, f"--hdrModel {model}"
    return method


def opencv(kind: str):
    def method(b: Bracket, work: Path):
        import cv2

        response = np.repeat(np.maximum(true_inverse(256), 1e-6).astype(np.float32)[:, None, None], 3, axis=2)
        t = time.perf_counter()
        frames = [cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in b.meta["paths"]]
        merger = cv2.createMergeDebevec() if kind == "debevec" else cv2.createMergeRobertson()
        hdr = merger.process(frames, b.times.astype(np.float32), response)
        return hdr[..., ::-1], time.perf_counter() - t, "true response"
    return method


def methods(case: str, meta: dict) -> dict:
    """label -> (callable(bracket, work), reason it cannot run or None)."""
    have = lambda *tools: next((f"{t} not installed" for t in tools if shutil.which(t) is None), None)  # noqa: E731
    if case == "raw":
        out = {f"hdrmerge-cli {k}": (lambda b, w, f=f, n=n: ours(b, f, w, f"ours{n}"), None)
               for n, (k, f) in enumerate(RAW_OURS.items())}
        s = meta["sensor"]
        noise = ["--noise", f"sigma_o2={s['sigma_o2_total']:.6g},alpha={s['alpha']:.6g}"]
        out["hdrmerge-cli defaults + true --noise"] = (lambda b, w: ours(b, noise, w, "ours-noise"), None)
        hm = have("hdrmerge") and "hdrmerge not installed (apt-get install hdrmerge)"
        out["HDRMerge (defaults)"] = (hdrmerge([]), hm)
        out["HDRMerge --no-align"] = (hdrmerge(["--no-align"]), hm)
        return out
    s = meta["sensor"]
    noise = ["--noise", f"sigma_o2={s['sigma_o2_total'] / SCALE**2:.6g},alpha={s['alpha'] / SCALE**2:.6g}"]
    out = {}
    for extra, tag in (([], ""), (noise, " + true --noise")):
        for k, f in LDR_OURS.items():
            n = len(out)
            out[f"hdrmerge-cli {k}{tag}"] = (lambda b, w, f=f + extra, n=n: ours(b, f, w, f"ours{n}"), None)
    for scale, tag in ((0.9, "low"), (1.1, "high")):  # the estimator chosen with a noise model off by 10 %
        off = ["--noise", f"sigma_o2={scale * s['sigma_o2_total'] / SCALE**2:.6g},"
                          f"alpha={scale * s['alpha'] / SCALE**2:.6g}"]
        out[f"hdrmerge-cli defaults + --noise 10 % {tag}"] = (lambda b, w, f=off, t=tag: ours(b, f, w, f"ours-{t}"),
                                                               None)
    pfs = have("pfsinhdrgen", "pfshdrcalibrate", "pfsout")
    lum = have("luminance-hdr-cli")
    out["pfstools (pfshdrcalibrate -f)"] = (pfstools, pfs and f"{pfs} (apt-get install pfstools)")
    for model in ("debevec", "robertson"):
        out[f"Luminance HDR {model}"] = (luminance(model), lum and f"{lum} (apt-get install luminance-hdr)")
    out["OpenCV MergeDebevec"] = (opencv("debevec"), None)
    out["OpenCV MergeRobertson"] = (opencv("robertson"), None)
    return out


# --- driver ------------------------------------------------------------------------------


def main(quick: bool = False) -> str:
    name = "cli_defaults_quick.md" if quick else "cli_defaults.md"
    if not (DATA / "hdr").is_dir():
        return f"cli_defaults: skipped, {DATA / 'hdr'} is missing\n"
    t_start = time.perf_counter()
    scenes, sweep, mp = (SCENES[:1], SHORT_SWEEP[1:2], 0.05) if quick else (SCENES, SHORT_SWEEP, 0.4)
    rows = {"raw": {}, "ldr": {}}  # case -> method -> [(psnr, below, invalid, below exact, below exact tight,
    #                                  seconds) or None per bracket]
    notes = {"raw": {}, "ldr": {}}  # case -> method -> {note: None}: skipped or failed, and how it resolved
    info = {"raw": [], "ldr": []}  # per bracket: (label, bound dB, fraction compared, width, height)
    with tempfile.TemporaryDirectory(prefix="cli_defaults.") as tmp:
        tmp = Path(tmp)
        for i, scene_name in enumerate(scenes):
            scene = prepare_scene(scene_name, mp, tmp / f"{scene_name}.exr")
            for j, (gain, sigma_o) in enumerate(sweep):
                for case, fmt in (("raw", "dng"), ("ldr", "tif")):
                    work = tmp / f"{case}-{i}-{j}"
                    work.mkdir()
                    meta = simulate(scene, fmt, gain, sigma_o, 10 * i + j, work / "bracket")
                    b = Bracket(meta, work / "bracket")
                    label = f"{scene_name.removeprefix('ScanLines_')} ({gain:g}, {sigma_o:g})"
                    info[case].append((label, b.crb_db, b.ok.mean(), meta["width"], meta["height"],
                                       b.exact[0][3], b.exact[1][3], b.exact[1][0].mean()))
                    for m, (fn, missing) in methods(case, meta).items():
                        result, note = None, missing
                        if not missing:
                            try:
                                est, seconds, note = fn(b, work)
                                result = (*b.score(est), seconds)
                            except Exception as exc:  # noqa: BLE001 - a failing peer is reported, not fatal
                                note = f"failed on {label}: {exc}"
                        rows[case].setdefault(m, []).append(result)
                        notes[case].setdefault(m, {})[note] = None
                    print(f"[cli_defaults] {case} {label}: {time.perf_counter() - t_start:.0f} s", file=sys.stderr,
                          flush=True)
    return write_result(RESULTS / name, report(rows, notes, info, quick, time.perf_counter() - t_start))


def report(rows, notes, info, quick, seconds) -> list[str]:
    sizes = " and ".join(dict.fromkeys(f"{x[3]} x {x[4]}" for x in info["raw"]))
    lines = ["# The command line with default options, against the Cramer-Rao bound and peers", "",
             f"`python -m benchmarks.cli_defaults{' --quick' if quick else ''}` at revision {revision()}; "
             f"{seconds:.0f} s.  "
             f"Simulated brackets (`hdrmerge-cli simulate`, protocol in the module docstring): "
             f"{len(info['raw'])} per case (scene x (sqrt(alpha), sigma_o) in 8-bit code units), "
             f"{sizes} pixels, 4 frames at {', '.join(TIMES)} s, 12-bit ADC.  PSNR of log E after one "
             f"global scale per method over the samples whose Cramer-Rao bound on Var[log E] is below {CRB_MAX:g}; "
             "'below CRB' = dB under that bound (0 = efficient; mean and worst over the brackets scored); "
             "'below exact CRB' = the same against the exact bound of the simulated files (Poisson "
             f"photo-electrons, `crb_log_counts`), over the samples where it is below {CRB_MAX:g} and, "
             f"'(< {CRB_TIGHT:g})', below {CRB_TIGHT:g}, where the bound on log E is approachable (near 1 no "
             "estimator reaches it: zero photon counts have no finite log); "
             "'invalid' = compared samples <= 0 or non-finite (floored); wall time of the whole command "
             "(OpenCV: in-process read + merge).", ""]
    titles = {"raw": "A. RAW: 12-bit DNG, `merge --cfa --reference T`, mosaic against the mosaicked truth",
              "ldr": "B. 8-bit TIFF through x^0.4 (`--crf gamma:2.5`), RGB against the truth"}
    for case in ("raw", "ldr"):
        labels = [x[0] for x in info[case]]
        lines += [f"## {titles[case]}", "",
                  "| method | settings / notes | scored | PSNR dB (mean) | below CRB dB (mean) | below CRB dB (worst) "
                  "| below exact CRB dB (mean) | (worst) | below exact CRB, < " f"{CRB_TIGHT:g} (mean) | (worst) "
                  "| invalid | wall s (mean) |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        per, per_x = [], []
        for m, r in rows[case].items():
            note = "; ".join(n for n in notes[case][m] if n)
            done = [x for x in r if x is not None]
            if not done:
                lines.append(f"| {m} | {note} | 0/{len(r)} | | | | | | | | | |")
                continue
            a = np.array(done)
            lines.append(f"| {m} | {note} | {len(done)}/{len(r)} | {a[:, 0].mean():.2f} | {a[:, 1].mean():.2f} | "
                         f"{a[:, 1].max():.2f} | {a[:, 3].mean():.2f} | {a[:, 3].max():.2f} | {a[:, 4].mean():.2f} | "
                         f"{a[:, 4].max():.2f} | {a[:, 2].mean():.2%} | {a[:, 5].mean():.2f} |")
            per.append(f"| {m} | " + " | ".join("-" if x is None else f"{x[1]:.2f}" for x in r) + " |")
            per_x.append(f"| {m} | " + " | ".join("-" if x is None else f"{x[3]:.2f} / {x[4]:.2f}" for x in r) + " |")
        crb = np.array([x[1] for x in info[case]])
        cov = np.array([x[2] for x in info[case]])
        lines += [f"| Cramer-Rao bound | | | {crb.mean():.2f} | 0 | 0 | 0 | 0 | 0 | 0 | | |", "",
                  f"Samples compared: {cov.mean():.1%} on average ({cov.min():.1%}-{cov.max():.1%}).", "",
                  "dB below the bound per bracket (scene (sqrt(alpha), sigma_o)):", "",
                  "| method | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels), *per,
                  "| bound PSNR dB | " + " | ".join(f"{x:.2f}" for x in crb) + " |", "",
                  f"dB below the exact bound per bracket, samples with exact CRB < {CRB_MAX:g} / < {CRB_TIGHT:g}:", "",
                  "| method | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels), *per_x,
                  "| bound PSNR dB | " + " | ".join(f"{x[5]:.2f} / {x[6]:.2f}" for x in info[case]) + " |",
                  f"| samples < {CRB_TIGHT:g} | " + " | ".join(f"{x[7]:.1%}" for x in info[case]) + " |", ""]
    return lines


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="one scene, one noise level, ~0.05 MP")
    print(main(ap.parse_args().quick))
