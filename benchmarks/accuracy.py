"""Accuracy against speed: every weighting and estimator of the project, OpenCV and
colour-hdri, on the same simulated brackets, next to the Cramer-Rao bound.

Two cases, each over the paper's gain/offset sweep (sqrt(alpha) in {0.25..4}, sigma_o in
{0.001..16}, in 8-bit codes of the linear signal, scaled by 4095/255 to the 12-bit ADC)
and four scenes (the built-in one and the three of ../shared/data/hdr), 4 frames each:

- ``raw``: RAW-like, 12-bit linear codes (identity CRF), 3 channels;
- ``jpeg``: JPEG-like, the 12-bit ADC output through the CRF x^0.4, re-quantised to 8 bits.

Frames are rendered in memory by the sensor model (16)-(18) (:mod:`hdrmerge_cli.core.sensor`)
and merged in memory: ours with :func:`~benchmarks.core_merge.merge_frames` (noise
and CRF known), OpenCV ``MergeDebevec``/``MergeRobertson`` with the known response (8-bit
inputs, as OpenCV requires: the RAW case's top 8 bits), colour-hdri ``image_stack_to_HDRI``
with the known CRF.  Also: IRLS passes, per-pixel evaluation of the weights instead of the
tables (same numbers, slower), and, for the JPEG case, the CRF estimated by the paper's QP
from N sampled pixels.  Accuracy: PSNR of log E (peak = the log range of the compared pixels,
those whose Cramer-Rao bound on log E is below 1) after one global scale per method (OpenCV
and colour-hdri have their own units); dB below the bound of the quantised, clipped codes.
Speed: time per megapixel of the merge on the same bracket.

    python -m benchmarks.accuracy [--quick]   # results/accuracy.md, accuracy_raw.png, accuracy_jpeg.png
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks import quiet_import, save_figure, write_result
from benchmarks.core_merge import merge_frames
from hdrmerge_cli.core.crf import CRF, table_crf
from hdrmerge_cli.core.noise import NoiseParams
from hdrmerge_cli.core.scene import procedural_scene
from hdrmerge_cli.core.sensor import SensorModel, auto_exposure_times, expose, quantise_crf, quantise_raw
from hdrmerge_cli.core.weights import WEIGHTING_FUNCTIONS
from hdrmerge_cli.core.weights_goossens2012 import log_normal_interval
from hdrmerge_cli.io.plots import pyplot

RESULTS = Path(__file__).parent / "results"
HDR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "hdr"
GAINS = (0.25, 0.5, 1.0, 2.0, 4.0)
SIGMAS = (0.001, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0)
GAMMA = 2.5
BITS = 12
SCALE = (2**BITS - 1) / 255.0
WEIGHTS = tuple(WEIGHTING_FUNCTIONS)
SIDE = 256  # scenes are resized to about SIDE x 1.5 SIDE pixels


def scenes(quick: bool, side: int = SIDE) -> dict[str, np.ndarray]:
    """Irradiance maps (H, W, 3), relative units, ~side x 1.5 side pixels."""
    out = {"built-in": procedural_scene(side, side * 3 // 2)}
    if quick:
        return out
    from hdrmerge_cli.io.images import read_exr

    for path in sorted(HDR.glob("*.exr")):
        img, _ = read_exr(path)
        step = max(1, int(np.ceil(img.shape[0] / side)))
        out[path.stem] = np.maximum(img[::step, ::step, :3].astype(np.float64), 0.0)
    return out


def render(scene: np.ndarray, case: str, gain: float, sigma_o: float, seed: int = 0):
    """A 4-frame bracket of ``scene``: codes, exposure times, irradiance in 12-bit codes per
    second (the truth), the sensor."""
    sensor = SensorModel(alpha=(gain * SCALE) ** 2, sigma_o2=max((sigma_o * SCALE) ** 2 - 1 / 12, 0.0), beta=0.0,
                         bits=BITS, black=0)
    # scene in electrons/s: the brightest 0.05 % at 90 % of saturation for t = 1
    e = scene / np.percentile(scene[scene > 0], 99.95) * 0.9 * sensor.saturation_electrons
    e = np.maximum(e, 1e-3 * e[e > 0].min())
    times = auto_exposure_times(e, sensor, 4)
    rng = np.random.default_rng(seed)
    frames = []
    for t in times:
        y = expose(e, t, sensor, rng, np.zeros(e.shape))
        frames.append(quantise_raw(y, sensor) if case == "raw" else quantise_crf(y, sensor, CRF("gamma", GAMMA), 8))
    return frames, times, e * np.sqrt(sensor.alpha), sensor


def crb_log(e: np.ndarray, times, gain: float, sigma_o2: float, full: float, case: str) -> np.ndarray:
    """Cramer-Rao bound on Var[log E] given a bracket's quantised, clipped codes: the
    inverse Fisher information sum_j sum_z (dP_j(z|E)/dlogE)^2 / P_j(z|E), with P_j a
    normal of mean ``mu = t E`` and variance ``sigma_o2 + gain mu`` (gain = sqrt(alpha))
    through the code bins: every code of a ``full``-scale linear ADC (``raw``) or 256
    codes through the CRF x^0.4 (``jpeg``).  ``e`` in linear code values per second."""
    if case == "raw":
        edges = np.arange(full + 2) - 0.5
    else:
        edges = CRF("gamma", GAMMA).inverse(np.clip((np.arange(257) - 0.5) / 255.0, 0, 1)) * full
    edges[0], edges[-1] = -np.inf, np.inf
    pdf = quiet_import("scipy.stats").norm.pdf
    info = np.zeros_like(e)
    for t in times:
        mu = t * e[:, None]
        sd = np.sqrt(sigma_o2 + gain * mu)
        dsd = gain / (2 * sd)  # d sd / d mu
        a, b = (edges[None, :-1] - mu) / sd, (edges[None, 1:] - mu) / sd
        p = np.exp(log_normal_interval(a, b))  # no cancellation in the tails
        fa, fb = np.clip(a, -40, 40), np.clip(b, -40, 40)  # phi(+-40) = 0 in float64
        # d/dmu Phi((c - mu)/sd) = -phi(x) (1 + x dsd) / sd with x = (c - mu) / sd; times mu: d / d log E
        dp = (-pdf(fb) * (1 + fb * dsd) + pdf(fa) * (1 + fa * dsd)) / sd * mu
        used = p > 1e-12  # bins of negligible probability carry negligible information
        info += np.sum(np.where(used, dp * dp / np.where(used, p, 1.0), 0.0), axis=1)
    return 1.0 / np.maximum(info, 1e-300)


def opencv_merge(kind: str, frames, times, case: str):
    def run():
        import cv2

        merger = cv2.createMergeDebevec() if kind == "debevec" else cv2.createMergeRobertson()
        return merger.process(z8, np.asarray(times, np.float32), response)

    z8 = [np.ascontiguousarray((f >> (BITS - 8)).astype(np.uint8)) if case == "raw" else f for f in frames]
    v = np.arange(256) / 255.0
    lin = v if case == "raw" else CRF("gamma", GAMMA).inverse(v)
    response = np.repeat(np.maximum(lin, 1e-6).astype(np.float32)[:, None, None], 3, axis=2)
    return run


def colour_merge(frames, times, case: str):
    full = 2**BITS - 1 if case == "raw" else 255
    data = [f / float(full) for f in frames]
    grid = np.linspace(0, 1, 256)
    crfs = None if case == "raw" else np.stack([CRF("gamma", GAMMA).inverse(grid)] * 3, axis=-1)

    def run():
        ch = quiet_import("colour_hdri")
        stack = ch.ImageStack()
        for d, t in zip(data, times):
            stack.append(ch.Image(data=d, metadata=ch.Metadata(f_number=1.0, exposure_time=float(t), iso=100)))
        return ch.image_stack_to_HDRI(stack, camera_response_functions=crfs)

    return run


def per_pixel_merge(frames, times, crf, full, weighting):
    """(7) with the weighting function evaluated on every pixel (no tables): the
    'per-pixel' option of the speed/error plot; classical weights only.  Pixels no frame
    measures are NaN here (scored at the median), not the tables' clipping bounds."""
    def run():
        num = np.zeros(frames[0].shape)
        den = np.zeros(frames[0].shape)
        for z, t in zip(frames, times):
            v = z / full
            lin = crf.inverse(v)
            w = WEIGHTING_FUNCTIONS[weighting](v, lin, None) * ((v > 0) & (v < 1))
            with np.errstate(divide="ignore"):
                num += w * np.where(lin > 0, np.log(np.maximum(lin, 1e-300)) - np.log(t), 0.0)
            den += w
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.exp(num / den)
    return run


def methods(frames, times, case, sensor, prior, quick):
    """name -> (family, callable returning the linear estimate)."""
    crf = CRF("linear") if case == "raw" else CRF("gamma", GAMMA)
    full = sensor.full_scale if case == "raw" else 255
    noise = [NoiseParams(sensor.sigma_o2_total, sensor.alpha, 0.0)] if case == "raw" else \
        [NoiseParams((sensor.sigma_o2_total) / SCALE**2, sensor.alpha / SCALE**2, 0.0)]
    black, white = 0.0, float(full)
    out = {}
    for est in ("log", "ml"):
        for w in WEIGHTS:
            out[f"{w}/{est}"] = ("ours", lambda w=w, est=est: merge_frames(frames, times, crf, black, white, w, noise,
                                                                           estimator=est, prior_rate=prior)[0])
    for it in (1, 3):
        out[f"probabilistic/log IRLS {it}"] = ("ours IRLS", lambda it=it: merge_frames(
            frames, times, crf, black, white, "probabilistic", noise, prior_rate=prior, irls_iterations=it)[0])
    out["triangle/log per-pixel"] = ("ours per-pixel", per_pixel_merge(frames, times, crf, full, "triangle"))
    out["OpenCV MergeDebevec"] = ("baseline", opencv_merge("debevec", frames, times, case))
    out["OpenCV MergeRobertson"] = ("baseline", opencv_merge("robertson", frames, times, case))
    out["colour-hdri"] = ("baseline", colour_merge(frames, times, case))
    if case == "jpeg":
        for n in ((500,) if quick else (100, 500, 2000)):
            out[f"probabilistic/log, CRF from {n} px"] = ("ours + estimated CRF",
                                                          estimated_crf_merge(frames, times, n, noise, prior))
    return out


def estimated_crf_merge(frames, times, samples, noise, prior):
    """The paper's QP (37) on ``samples`` pixels, then the merge with that CRF."""
    from hdrmerge_cli.core.crf_estimate import CRF_ESTIMATORS, inverse_from_log, sample_pixels

    method = CRF_ESTIMATORS["goossens"]

    def run():
        rng = np.random.default_rng(0)
        codes = np.stack([f.reshape(-1, 3) for f in frames], axis=-1)  # (N, 3, P)
        mid = codes[:, :, len(frames) // 2]
        tables = [inverse_from_log(method.estimate(codes[sample_pixels(mid[:, c], samples, rng), c, :], np.log(times),
                                                   256, method.smoothing).g)[0] for c in range(3)]
        crf = table_crf(np.stack(tables))
        return merge_frames(frames, times, crf, 0.0, 255.0, "probabilistic", noise, prior_rate=prior)[0]

    return run


def evaluate(case: str, scene: np.ndarray, gain: float, sigma_o: float, quick: bool = False, only=None) -> dict:
    """Per method (all, or those named in ``only``): (family, PSNR dB, dB below the CRB,
    seconds per MP) on one bracket; also ``crb`` (dB) and ``coverage``."""
    frames, times, e_codes, sensor = render(scene, case, gain, sigma_o)
    lum = e_codes.reshape(-1)
    grid = np.geomspace(max(lum.min(), 1e-6), lum.max(), 300)
    crb = np.exp(np.interp(np.log(np.maximum(lum, 1e-6)), np.log(grid), np.log(crb_log(grid, times, np.sqrt(sensor.alpha), sensor.sigma_o2_total,
                                                                         sensor.full_scale, case))))
    ok = crb < 1.0
    log_t = np.log(lum[ok])
    peak2 = np.ptp(log_t) ** 2
    crb_db = 10 * np.log10(peak2 / np.mean(crb[ok]))
    mid = frames[len(frames) // 2]
    crf = CRF("linear") if case == "raw" else CRF("gamma", GAMMA)
    full = sensor.full_scale if case == "raw" else 255
    lin_mid = crf.inverse(np.clip(mid / full, 0, 1))
    prior = float(np.mean(lin_mid[(lin_mid > 0) & (lin_mid < 1)]) * full / times[len(frames) // 2])
    mp = lum.size / 3 / 1e6
    out = {"crb": crb_db, "coverage": float(ok.mean())}
    for name, (family, run) in methods(frames, times, case, sensor, prior, quick).items():
        if only is not None and name not in only:
            continue
        t = time.perf_counter()
        est = np.asarray(run(), np.float64).reshape(-1)
        dt = time.perf_counter() - t
        le = np.log(np.maximum(est[ok], 1e-30))
        good = np.isfinite(le)
        le = np.where(good, le, np.median(le[good]))
        le -= np.median(le - log_t)  # one global scale per method
        psnr = 10 * np.log10(peak2 / np.mean((le - log_t) ** 2))
        out[name] = (family, psnr, crb_db - psnr, dt / mp)
    return out


#: the shared scenes are run at three operating points of the sweep (low, mid, high noise)
SHORT_SWEEP = ((4.0, 0.5), (1.0, 2.0), (0.25, 16.0))


def main(quick: bool = False) -> str:
    t0 = time.perf_counter()
    side = 128 if quick else SIDE
    evaluate("raw", procedural_scene(32, 48), 1.0, 1.0, quick)  # warm up: imports, JIT compilation
    evaluate("jpeg", procedural_scene(32, 48), 1.0, 1.0, quick)
    results = {case: [] for case in ("raw", "jpeg")}
    all_scenes = scenes(quick, side)
    for name, scene in all_scenes.items():
        sweep = [(1.0, 1.0), (1.0, 8.0)] if quick else (
            [(g, s) for g in GAINS for s in SIGMAS] if name == "built-in" else SHORT_SWEEP)
        for case in results:
            for g, s in sweep:
                results[case].append(evaluate(case, scene, g, s, quick))
    n = len(results["raw"])
    lines = ["# Accuracy against speed", "",
             f"{n} brackets per case ({'the built-in scene at 2 operating points' if quick else 'the built-in scene over the paper sweep of 35 (sqrt(alpha), sigma_o) pairs, the 3 shared scenes at 3 of them'}), "
             f"4 frames of ~{side} x {side * 3 // 2} pixels; {time.perf_counter() - t0:.0f} s.  PSNR of log E after one global scale per "
             "method; 'below CRB' = dB under the Cramer-Rao bound of the quantised, clipped codes (0 is perfect); "
             "s/MP = merge time per megapixel on these small brackets (table building included).", ""]
    for case, rows in results.items():
        names = [k for k in rows[0] if k not in ("crb", "coverage")]
        lines += [f"## {case}: " + ("12-bit linear codes" if case == "raw" else "8-bit codes through x^0.4"), "",
                  "| method | family | PSNR dB (mean) | below CRB dB (mean) | below CRB dB (worst) | s/MP (median) |",
                  "|---|---|---|---|---|---|"]
        stats = {}
        for n in names:
            fam = rows[0][n][0]
            ps = np.array([r[n][1] for r in rows])
            below = np.array([r[n][2] for r in rows])
            spm = np.median([r[n][3] for r in rows])
            stats[n] = (fam, below.mean(), spm)
        for n in sorted(names, key=lambda n: stats[n][1]):
            ps = np.array([r[n][1] for r in rows])
            below = np.array([r[n][2] for r in rows])
            lines.append(f"| {n} | {stats[n][0]} | {ps.mean():.2f} | {below.mean():.2f} | {below.max():.2f} | "
                         f"{stats[n][2]:.3f} |")
        crb = np.array([r["crb"] for r in rows])
        cov = np.mean([r["coverage"] for r in rows])
        lines += [f"| Cramer-Rao bound | | {crb.mean():.2f} | 0 | 0 | |", "",
                  f"Pixels compared: {cov:.1%} on average (CRB of log E below 1).", ""]
        plot(case, stats, RESULTS / f"accuracy_{case}{'_quick' if quick else ''}.png")
    return write_result(RESULTS / ("accuracy_quick.md" if quick else "accuracy.md"), lines)


def plot(case: str, stats: dict, out: Path) -> None:
    fig, ax = pyplot().subplots(figsize=(8, 5.5))
    markers = {"ours": "o", "ours IRLS": "D", "ours per-pixel": "v", "baseline": "s", "ours + estimated CRF": "^"}
    for fam, marker in markers.items():
        pts = [(spm, below, n) for n, (f, below, spm) in stats.items() if f == fam]
        if not pts:
            continue
        x, y, names = zip(*pts)
        ax.scatter(x, y, marker=marker, label=fam, s=30)
        for xi, yi, n in zip(x, y, names):
            ax.annotate(n, (xi, yi), fontsize=6, xytext=(3, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_xlabel("seconds per megapixel (4 frames)")
    ax.set_ylabel("dB below the Cramer-Rao bound (lower is better)")
    ax.set_title(f"{case}: accuracy against speed")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    save_figure(fig, out)


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="the built-in scene, two operating points")
    print(main(ap.parse_args().quick))
