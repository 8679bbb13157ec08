"""CRF estimation on the 101 real camera response curves of DoRF.

A real HDR scene (``ScanLines_StillLife.exr``, luminance, 282 x 414 pixels) is exposed in
5 frames 2 stops apart through the sensor model (Poisson photons, Gaussian read noise,
clipping) at three noise levels, mapped through each DoRF curve and quantised to 8 bits.
Every method estimates ``g(z) = log gamma^-1(z)`` from the same bracket; the error is the
RMSE of ``g - g_true`` after removing the mean difference, over the codes the noise-free
bracket produces whose linear signal is above the read noise and whose quantisation bin is
narrower than 10 % of the signal (below that no method can know the curve).  OpenCV's
``createCalibrateDebevec`` (70 samples, lambda 10: its defaults) and
``createCalibrateRobertson`` run on the same frames in the same process.

    python -m benchmarks.crf_dorf [--quick]   # writes benchmarks/results/crf_dorf.md
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks import write_result
from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS
from hdrmerge_cli.io.images import read_exr

SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data"
#: noise level -> (photo-electrons at full scale, read-noise std as a fraction of full scale)
LEVELS = {"low": (20000, 0.0005), "moderate": (2000, 0.002), "high": (300, 0.006)}
FRAMES, STOPS = 5, 2.0


def scene(step: int = 3) -> np.ndarray:
    """(H, W) luminance of the scene, median 1."""
    img = read_exr(str(SHARED / "hdr" / "ScanLines_StillLife.exr"))[0][::step, ::step, :3].mean(axis=-1)
    img = np.maximum(img.astype(np.float64), 0.0)
    return img / np.median(img[img > 0])


def bracket(e: np.ndarray, curve: int, level: str, rng: np.random.Generator):
    """Codes (H, W, P) uint8, times (P,), the true g (256,) and the evaluated codes (256,) bool."""
    curves = np.load(SHARED / "crf" / "dorf_train.npz")
    bright, irr = curves["brightness"][curve], curves["irradiance"][curve]
    full_e, read = LEVELS[level]
    times = 0.18 * 2.0 ** (STOPS * (np.arange(FRAMES) - FRAMES // 2))
    frames, clean = [], []
    for t in times:
        x = rng.poisson(np.minimum(e * t, 4.0) * full_e) / full_e + rng.normal(0.0, read, e.shape)
        for signal, out in ((x, frames), (e * t, clean)):
            out.append(np.rint(255 * np.interp(np.clip(signal, 0, 1), irr, bright)).astype(np.uint8))
    b_u, first = np.unique(bright, return_index=True)
    inv = lambda c: np.interp(c / 255.0, b_u, irr[first])  # noqa: E731
    codes = np.arange(256.0)
    lin = inv(codes)
    with np.errstate(divide="ignore"):
        g_true = np.log(lin)
    ev = np.zeros(256, bool)
    ev[np.unique(np.stack(clean))] = True
    ev[[0, 255]] = False
    ev &= (lin > read) & (inv(codes + 0.5) - inv(codes - 0.5) < 0.1 * lin)
    return np.stack(frames, axis=-1), times, g_true, ev


def rmse(g: np.ndarray, g_true: np.ndarray, ev: np.ndarray) -> float:
    d = g[ev] - g_true[ev]
    return float(np.sqrt(np.mean((d - d.mean()) ** 2)))


def ours(name: str, samples: int | None = None, **options):
    method = CRF_ESTIMATORS[name]

    def run(frames, times, rng):
        codes = frames.reshape(-1, frames.shape[-1])
        n = samples or method.samples
        if n and n < len(codes):
            codes = codes[rng.choice(len(codes), n, replace=False)]
        kw = {} if method.smoothing is None else {"smoothing": method.smoothing}
        return method.estimate(codes, np.log(times), 256, **kw, **options).g

    return run


def opencv(kind: str):
    import cv2

    def run(frames, times, rng):
        imgs = [np.repeat(frames[..., j, None], 3, axis=-1) for j in range(frames.shape[-1])]
        cal = cv2.createCalibrateDebevec() if kind == "debevec" else cv2.createCalibrateRobertson()
        resp = cal.process(imgs, times.astype(np.float32))[:, 0, 0].astype(np.float64)
        return np.log(np.maximum(resp, 1e-12))

    return run


METHODS = {
    "goossens": ours("goossens"),
    "goossens (triangle w)": ours("goossens", weighting="triangle"),
    "debevec": ours("debevec"),
    "robertson": ours("robertson"),
    "opencv Debevec": opencv("debevec"),
    "opencv Robertson": opencv("robertson"),
}


def evaluate(methods: dict, curves, levels, e) -> dict:
    out = {}
    for level in levels:
        for k in curves:
            frames, times, g_true, ev = bracket(e, k, level, np.random.default_rng(k))
            for name, run in methods.items():
                t0 = time.perf_counter()
                g = run(frames, times, np.random.default_rng(1000 + k))
                dt = time.perf_counter() - t0
                inside = np.flatnonzero(ev)
                mono = bool(np.all(np.diff(g[inside[0]:inside[-1] + 1]) > 0))
                out.setdefault((level, name), []).append((rmse(g, g_true, ev), dt, mono))
    return out


def main(quick: bool = False) -> str:
    if not (SHARED / "crf" / "dorf_train.npz").exists():
        return f"crf_dorf: skipped ({SHARED / 'crf' / 'dorf_train.npz'} not found: the DoRF curves live in ../shared/data)"
    curves = range(0, 101, 10 if quick else 1)
    e = scene()
    res = evaluate(METHODS, curves, LEVELS, e)
    lines = [
        f"# CRF estimation on DoRF curves ({len(curves)} curves, {FRAMES} frames {STOPS:g} stops apart, "
        f"{e.size} pixels, 8-bit)", "",
        "RMSE of g = log gamma^-1 (natural log units, constant removed) over the exposed codes; time per bracket "
        "(all channels share one curve here: one channel solved).", "",
        "| noise | method | median RMSE | 90th pct RMSE | mean time (s) | non-monotone curves |",
        "|---|---|---|---|---|---|",
    ]
    for (level, name), v in res.items():
        a = np.array([(r, t) for r, t, _ in v])
        bad = sum(not m for _, _, m in v)
        lines.append(f"| {level} | {name} | {np.median(a[:, 0]):.4f} | {np.percentile(a[:, 0], 90):.4f} | "
                     f"{a[:, 1].mean():.3f} | {bad}/{len(v)} |")
    # speed against error: pixels sampled
    sweep = {f"goossens, {n or 'all'} px": ours("goossens", n) for n in (1000, 10000, 100000, None)}
    sweep |= {f"debevec, {n} px": ours("debevec", n) for n in (100, 1000, 5000)}
    res = evaluate(sweep, range(0, 101, 20 if quick else 5), ["moderate"], e)
    lines += ["", "Speed against error (moderate noise): pixels sampled per channel.", "",
              "| method | median RMSE | 90th pct RMSE | mean time (s) |", "|---|---|---|---|"]
    for (_, name), v in res.items():
        a = np.array([(r, t) for r, t, _ in v])
        lines.append(f"| {name} | {np.median(a[:, 0]):.4f} | {np.percentile(a[:, 0], 90):.4f} | {a[:, 1].mean():.3f} |")
    return write_result(Path(__file__).parent / "results" / ("crf_dorf_quick.md" if quick else "crf_dorf.md"), lines)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="every 10th curve (11 of 101)")
    print(main(ap.parse_args().quick))
