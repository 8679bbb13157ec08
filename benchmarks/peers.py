"""Peer HDR programs, run side by side on the same 8-bit frames for a leave-one-out benchmark.

Each peer is given in-memory 8-bit RGB frames and their exposure times (no EXIF), recovers
its own camera response from them, merges a radiance map, and returns both
(:class:`PeerResult`), so that the caller can predict a left-out frame's codes through that
peer's response (:func:`predict_codes`).  Convention of every result: ``response[c, z]`` is
in the units of ``radiance[..., c] * t`` for a pixel of code ``z`` in a frame of exposure
``t`` (checked on the well-exposed pixels of a real JPEG bracket: median of
``response[c, z] / (radiance * t)`` per input frame within ~5 % of 1 on the middle frames for
every peer, 10-20 % off on the extreme frames, where the peers' fits are worst).

Peers (:data:`PEERS`), all with their default settings unless said:

- ``opencv-debevec``: OpenCV ``createCalibrateDebevec()`` (70 samples, lambda 10) then
  ``createMergeDebevec()`` with that response; response = the calibrated ``(256, 1, 3)``
  table (BGR, reordered to RGB).
- ``opencv-robertson``: OpenCV ``createCalibrateRobertson()`` (30 iterations, threshold
  0.01) then ``createMergeRobertson()`` with that response; response as above.
- ``colour-hdri``: :func:`colour_hdri.camera_response_functions_Debevec1997` (Grossberg 2003
  histogram sampling, Debevec hat weight, lambda 30, polynomial extrapolation of the
  zero-weight ends, normalised to max 1) then :func:`colour_hdri.image_stack_to_HDRI` with
  that CRF; frames as float ``codes / 255``, metadata f/1, ISO 100.  colour-hdri divides by
  the average luminance ``k N^2 / (t S)`` (k = 12.5), so ``radiance * t = CRF * k N^2 / S``:
  response = CRF x ``average_luminance(1, 1, 100)`` (= 0.125).
- ``luminance-robertson``: ``luminance-hdr-cli --hdrModel robertsonauto --hdrWeight
  triangular`` (initial response linear, the default), ``-e log2(t)`` per frame (Luminance
  HDR's "EV" is the frame's exposure-time scale ``2**EV``, so ``EV = log2(t)`` gives its
  radiance in the units of ``response / t``), HDR saved as EXR with ``-s``; response read
  from ``--outputCameraResponseCurve`` (a 4096-bin CSV, bins filled piecewise constant
  between codes: code ``z`` is read at bin ``round(z * 4095 / 255)``).
- ``luminance-debevec``: Luminance HDR only self-calibrates with Robertson's method
  (``robertsonauto``), so two runs: the ``robertsonauto`` run above writes the response
  curve, then ``--hdrModel debevec --hdrResponseCurve from_file --inputCameraResponseCurve
  curve.csv`` merges.  Luminance's Debevec merge rescales each frame to its own min..max
  before the response lookup and averages in the log domain, so the curve file is not
  consistent with its radiance: the response is recovered from that radiance instead, per
  channel and code ``z`` the median of ``radiance * t`` over the pixels of all input frames
  having code ``z``, empty codes filled by interpolation, made non-decreasing.  ``seconds``
  counts both runs.
- ``pfstools``: ``pfsinhdrgen`` (hdrgen script lines ``file 1/t 1 100 0``, i.e. f/1 and
  ISO 100) ``| pfshdrcalibrate -c robertson -s response.m | pfsout out.exr`` (short options:
  the Debian 2.2.0 binary rejects the man page's ``--calibration``): its default Robertson
  2002 self-calibration (initial response linear, Gaussian weight sigma 0.2) and pfstools
  2.2's noise-aware merge (Hanji et al. 2020, Poisson photon noise).  The response is read
  from the saved Octave text file (IR, IG, IB matrices).  pfstools outputs absolute units
  (cd/m^2 from the BV of the hdrgen script), one global constant away from the response's:
  the response is rescaled by the median of ``radiance * t / response[z]`` over the input
  frames' pixels with 16 <= z <= 239.

Every response is made non-decreasing (``np.maximum.accumulate``, positive).  ``seconds``
is wall time of calibrate + merge; for CLI peers it includes writing the input frames
(8-bit TIFF), subprocess start-up and reading the outputs (EXR via OpenImageIO).
colour-hdri's time is dominated by a dense ``numpy.linalg.lstsq`` per channel (~1 s each on
one core for 6 frames): on a loaded machine, multithreaded BLAS can make it 10-20x slower, so
time it with ``OPENBLAS_NUM_THREADS=1`` (or on an idle machine).

Versions used when written: OpenCV 5.0 (pip ``opencv-python-headless``), colour-hdri 0.2.6
(pip ``colour-hdri``), Luminance HDR 2.6.1.1 and pfstools 2.2.0 (Debian 12).  Install the
CLI peers with ``apt-get install luminance-hdr pfstools``; OpenCV and colour-hdri are pip
dependencies of the project.  Luminance HDR runs with ``QT_QPA_PLATFORM=offscreen``.
"""
from __future__ import annotations

import importlib
import os
import shutil
import subprocess
import time as _time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

PEERS = ("opencv-debevec", "opencv-robertson", "colour-hdri",
         "luminance-debevec", "luminance-robertson", "pfstools")
TIMEOUT = 600  # s, per subprocess
_CODES = np.arange(256, dtype=np.float64)


@dataclass
class PeerResult:
    radiance: np.ndarray  # (H, W, 3) float64, the peer's merged HDR, in the peer's own units
    response: np.ndarray  # (3, 256) float64 non-decreasing, response[c, z] ~ radiance[..., c] * t
    seconds: float  # wall time of calibrate + merge (incl. subprocesses and file I/O for CLIs)


def available() -> dict[str, str | None]:
    """Peer name -> ``None`` if runnable, else a one-line reason."""

    def module(name, pip):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                importlib.import_module(name)
        except Exception as exc:  # noqa: BLE001 - any import failure makes the peer unavailable
            return f"{name} not importable ({type(exc).__name__}; pip install {pip})"
        return None

    def tools(names, apt):
        missing = [n for n in names if shutil.which(n) is None]
        return f"{', '.join(missing)} not installed (apt-get install {apt})" if missing else None

    exr = module("OpenImageIO", "OpenImageIO")
    cv = module("cv2", "opencv-python-headless")
    lum = tools(["luminance-hdr-cli"], "luminance-hdr") or cv or exr  # cv2 writes the TIFFs
    return {"opencv-debevec": cv, "opencv-robertson": cv,
            "colour-hdri": module("colour_hdri", "colour-hdri"),
            "luminance-debevec": lum, "luminance-robertson": lum,
            "pfstools": tools(["pfsinhdrgen", "pfsin", "pfshdrcalibrate", "pfsout"], "pfstools")
            or cv or exr}


def run_peer(name: str, frames: list[np.ndarray], times: list[float], workdir: Path) -> PeerResult:
    """Calibrate and merge ``frames`` ((H, W, 3) uint8 RGB, increasing exposure) with peer ``name``."""
    if name not in PEERS:
        raise ValueError(f"unknown peer {name!r}; one of {', '.join(PEERS)}")
    if len(frames) != len(times) or len(frames) < 2:
        raise ValueError("need at least two frames, one exposure time each")
    frames = [np.ascontiguousarray(f, dtype=np.uint8) for f in frames]
    times = [float(t) for t in times]
    if any(f.ndim != 3 or f.shape[2] != 3 or f.shape != frames[0].shape for f in frames):
        raise ValueError("frames must all be (H, W, 3) RGB of one size")
    if not all(np.isfinite(t) and t > 0 for t in times):
        raise ValueError("exposure times must be positive")
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    runner = {"opencv-debevec": _opencv, "opencv-robertson": _opencv, "colour-hdri": _colour_hdri,
              "luminance-debevec": _luminance, "luminance-robertson": _luminance,
              "pfstools": _pfstools}[name]
    radiance, response, seconds = runner(name, frames, times, workdir)
    response = np.maximum.accumulate(np.maximum(np.asarray(response, np.float64), 1e-30), axis=1)
    return PeerResult(np.asarray(radiance, np.float64), response, seconds)


def predict_codes(result: PeerResult, time: float) -> np.ndarray:
    """(H, W, 3) float64 codes (0..255) predicted for a frame of exposure ``time``: the inverse of
    ``result.response`` per channel at ``radiance * time``."""
    e = result.radiance * float(time)
    out = np.empty(e.shape, np.float64)
    for c in range(3):
        out[..., c] = np.interp(e[..., c], result.response[c], _CODES)
    return np.clip(out, 0.0, 255.0)


# --- in-process peers --------------------------------------------------------------------


def _opencv(name, frames, times, workdir):
    import cv2

    bgr = [np.ascontiguousarray(f[..., ::-1]) for f in frames]
    t = np.asarray(times, np.float32)
    start = _time.perf_counter()
    if name == "opencv-debevec":
        response = cv2.createCalibrateDebevec().process(bgr, t)
        hdr = cv2.createMergeDebevec().process(bgr, t, response)
    else:
        response = cv2.createCalibrateRobertson().process(bgr, t)
        hdr = cv2.createMergeRobertson().process(bgr, t, response)
    seconds = _time.perf_counter() - start
    return hdr[..., ::-1], response[:, 0, ::-1].T, seconds


def _colour_hdri(name, frames, times, workdir):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        import colour_hdri as ch

        start = _time.perf_counter()
        stack = ch.ImageStack()
        for f, t in zip(frames, times):
            meta = ch.Metadata(f_number=1.0, exposure_time=t, iso=100.0)
            stack.append(ch.Image(data=f / 255.0, metadata=meta))
        crfs = ch.camera_response_functions_Debevec1997(stack)  # (256, 3), before the merge clears data
        radiance = ch.image_stack_to_HDRI(stack, camera_response_functions=crfs)
        seconds = _time.perf_counter() - start
    return radiance, crfs.T * float(ch.average_luminance(1.0, 1.0, 100.0)), seconds


# --- command-line peers ------------------------------------------------------------------


#: the environment Qt programs (Luminance HDR, HDRMerge) need without a screen
QT = {"QT_QPA_PLATFORM": "offscreen"}


def run_tool(cmd, cwd, stdin=None, stdout=subprocess.DEVNULL, env=None) -> str:
    """Run a peer's command ``cmd`` (list) in ``cwd`` with :data:`TIMEOUT`; ``env``: variables
    added to this process's environment.  Returns its stderr; RuntimeError naming the tool,
    its exit status and the last line of its stderr when it fails."""
    cmd = [str(c) for c in cmd]
    try:
        proc = subprocess.run(cmd, cwd=cwd, stdin=stdin, stdout=stdout, stderr=subprocess.PIPE,
                              env=dict(os.environ, **(env or {})), timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        raise RuntimeError(f"{Path(cmd[0]).name} timed out after {TIMEOUT} s") from None
    err = proc.stderr.decode(errors="replace")
    if proc.returncode != 0:
        tail = err.strip().splitlines()[-1:] or [""]
        raise RuntimeError(f"{Path(cmd[0]).name} failed (exit {proc.returncode}): {tail[0][:200]}")
    return err


def _write_tiffs(frames, workdir):
    import cv2

    names = [f"frame{i:02d}.tif" for i in range(len(frames))]
    for n, f in zip(names, frames):
        if not cv2.imwrite(str(workdir / n), np.ascontiguousarray(f[..., ::-1])):
            raise RuntimeError(f"cannot write {workdir / n}")
    return names


def read_exr_rgb(path) -> np.ndarray:
    """(H, W, 3) float64 R, G, B of an EXR, by channel name."""
    from hdrmerge_cli.io.images import read_exr

    pixels, attrs = read_exr(path)
    names = list(attrs["channelnames"])
    return pixels[..., [names.index(c) for c in "RGB"]].astype(np.float64)


def _luminance(name, frames, times, workdir):
    start = _time.perf_counter()
    files = _write_tiffs(frames, workdir)
    ev = ",".join(f"{np.log2(t):.6f}" for t in times)
    base = ["luminance-hdr-cli", "-e", ev, "--hdrWeight", "triangular"]
    run_tool(base + ["--hdrModel", "robertsonauto", "--outputCameraResponseCurve", "curve.csv",
                 "-s", "robertson.exr", *files], workdir, env=QT)
    if name == "luminance-debevec":
        run_tool(base + ["--hdrModel", "debevec", "--hdrResponseCurve", "from_file",
                     "--inputCameraResponseCurve", "curve.csv", "-s", "debevec.exr", *files],
             workdir, env=QT)
        radiance = read_exr_rgb(workdir / "debevec.exr")
        seconds = _time.perf_counter() - start
        return radiance, _response_from_radiance(frames, times, radiance), seconds
    radiance = read_exr_rgb(workdir / "robertson.exr")
    curve = np.loadtxt(workdir / "curve.csv", delimiter=",", skiprows=1)[:, 1::2]  # Ir, Ig, Ib
    seconds = _time.perf_counter() - start
    bins = np.round(_CODES * (len(curve) - 1) / 255).astype(int)
    return radiance, curve[bins].T, seconds


def _pfstools(name, frames, times, workdir):
    start = _time.perf_counter()
    files = _write_tiffs(frames, workdir)  # relative names: pfsinhdrgen cannot take spaces
    script = "".join(f"{n} {1.0 / t!r} 1 100 0\n" for n, t in zip(files, times))  # 1/t, f/1, ISO 100
    (workdir / "stack.hdrgen").write_text(script)
    with open(workdir / "stack.pfs", "wb") as out:
        err = run_tool(["pfsinhdrgen", "stack.hdrgen"], workdir, stdout=out)
    if err.strip():  # it exits 0 and skips a frame that pfsin cannot read: silent only on success
        raise RuntimeError(f"pfsinhdrgen failed: {err.strip()[-1500:]}")
    with open(workdir / "stack.pfs", "rb") as inp, open(workdir / "hdr.pfs", "wb") as out:
        run_tool(["pfshdrcalibrate", "-c", "robertson", "-s", "response.m"], workdir, stdin=inp, stdout=out)
    with open(workdir / "hdr.pfs", "rb") as inp:
        run_tool(["pfsout", "out.exr"], workdir, stdin=inp)
    radiance = read_exr_rgb(workdir / "out.exr")
    mats = _octave_matrices(workdir / "response.m")
    seconds = _time.perf_counter() - start
    response = np.stack([mats[k][:, 2] for k in ("IR", "IG", "IB")])  # log10 | code | response
    # pfstools' radiance is absolute (cd/m^2): one global constant away from the response.
    ratios = []
    for f, t in zip(frames, times):
        ok = (f >= 16) & (f <= 239) & (radiance > 0) & np.isfinite(radiance)
        looked_up = np.stack([response[c][f[..., c]] for c in range(3)], axis=-1)
        ratios.append((radiance * t)[ok] / looked_up[ok])
    return radiance, response * np.median(np.concatenate(ratios)), seconds


def _octave_matrices(path):
    """The named matrices of an Octave text file (``# name:`` headers, numeric rows)."""
    mats, cur = {}, None
    for line in Path(path).read_text().splitlines():
        if line.startswith("# name:"):
            cur = line.split(":", 1)[1].strip()
            mats[cur] = []
        elif cur is not None and line.strip() and not line.startswith("#"):
            mats[cur].append([float(x) for x in line.split()])
    return {k: np.array(v) for k, v in mats.items()}


def _response_from_radiance(frames, times, radiance):
    """(3, 256): per channel and code z, the median of ``radiance * t`` over the pixels of all
    frames having code z; empty codes interpolated, then made non-decreasing."""
    response = np.empty((3, 256))
    for c in range(3):
        z = np.concatenate([f[..., c].ravel() for f in frames])
        e = np.concatenate([(radiance[..., c] * t).ravel() for t in times])
        order = np.argsort(z, kind="stable")
        z, e = z[order], e[order]
        edges = np.searchsorted(z, np.arange(257))
        have = edges[1:] > edges[:-1]
        med = np.array([np.median(e[a:b]) for a, b in zip(edges[:-1][have], edges[1:][have])])
        response[c] = np.interp(_CODES, _CODES[have], med)
    return np.maximum.accumulate(response, axis=1)
